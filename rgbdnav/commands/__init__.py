"""One module per CLI verb (`odometry`, `board`, `export`, `fleet`, `batch`); nothing else.

The verbs whose work other verbs reuse (`map`, `localize`, `eval`, `navigate`) keep it in
`rgbdnav/runners/`. A command wires the layers below it (`runners/`, the shared pieces in
`rgbdnav/`, sensors, slam, nav) and never imports another command.
"""
