"""``python -m kpstudy``: see :mod:`kpstudy.cli`."""

import sys

try:
    from kpstudy.cli import main

    sys.exit(main())
except KeyboardInterrupt:  # Ctrl-C before main() took over (while importing)
    print("kpstudy: interrupted", file=sys.stderr)
    sys.exit(130)
