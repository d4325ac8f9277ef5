"""``python -m emr_client``: see ``emr_client.cli``."""

import sys

from .cli import main

sys.exit(main())
