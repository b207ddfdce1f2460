"""`python -m srfpipe ...`: the same as the `srfpipe` command (srfpipe.cli)."""

import sys

from srfpipe.cli import main

if __name__ == "__main__":
    sys.exit(main())
