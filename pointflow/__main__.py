"""``python -m pointflow``: the ``pointflow`` command (:mod:`pointflow.cli`)."""
import sys

from .cli import main

sys.exit(main())
