"""`python -m rig ...`: the same command line as the `rig` script (`rig.cli.main`)."""

from rig.cli import main

raise SystemExit(main())
