"""One module per ``rig`` sub-command; each defines ``register(subparsers)``.

Modules import their heavy dependencies (Mitsuba, matplotlib) inside the command
function so that ``rig --help`` and quick commands start fast.
"""
