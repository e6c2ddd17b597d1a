import sys

from cvxnav.cli import main

sys.exit(main())
