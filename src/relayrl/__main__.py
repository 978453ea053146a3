"""`python -m relayrl ...` runs the `relayrl` command."""

import sys

from relayrl.cli import main

sys.exit(main())
