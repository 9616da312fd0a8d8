"""``python -m radarpc ...`` is the ``radarpc`` command."""
import sys

from radarpc.cli import main

sys.exit(main())
