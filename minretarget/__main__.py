"""``python -m minretarget``: the same as the ``minretarget`` command."""
import sys

from .cli import main

sys.exit(main())
