import sys

from magctl.cli import main

sys.exit(main())
