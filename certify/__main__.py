"""`python -m certify ...`: the same command line as the `certify` script."""

import sys

from certify.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
