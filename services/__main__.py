import sys

from wavegrasp.cli import main

sys.exit(main())
