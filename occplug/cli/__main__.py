"""``python -m occplug.cli`` runs the ``occplug`` command."""

import sys

from occplug.cli import main

sys.exit(main())
