"""One module per CLI verb (`odometry`, `map`, `localize`, `eval`, `navigate`, `board`).

A command wires the layers below it (sensors, slam, nav and the shared pieces in `rgbdnav/`)
and never imports another command.
"""
