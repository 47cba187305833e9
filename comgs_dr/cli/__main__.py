"""``python -m comgs_dr.cli``: the ``comgs`` command."""
import sys

from comgs_dr.cli import main

sys.exit(main())
