"""``python -m BoneWatertightLib``: see :mod:`BoneWatertightLib.app.cli`."""

import sys

from .app.cli import main

if __name__ == "__main__":
    sys.exit(main())
