"""The work of the verbs that other verbs reuse: `map`, `localize`, `eval`, `navigate`.

Layers inside `rgbdnav/`: `cli.py` parses flags -> `commands/` and `live/` (one verb each) ->
`runners/` (a run: inputs + `Config` in, run directory and summary out) -> the shared pieces
(`config`, `run_dir`, `report`, `scan_stream`, `visualize`, ...) -> `sensors/`, `slam/`, `nav/`.
A command built from other verbs (`batch`) calls their runs here, never another command; a run
never imports a command, the live run or another run (`tests/test_house_rules.py` checks it).
Not named `runs/`: that is the git-ignored output folder.
"""
