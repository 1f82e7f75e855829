"""`python -m rig ...`: the same command line as the `rig` script (`rig.cli.run`)."""

from rig.cli import run

run()
