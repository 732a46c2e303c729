import sys

from kpstudy.cli import main

sys.exit(main())
