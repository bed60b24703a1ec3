import sys

from torchevtrack.cli import main

sys.exit(main())
