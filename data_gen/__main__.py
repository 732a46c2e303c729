"""``python -m data_gen``: see :mod:`data_gen.cli`."""

import sys

try:
    from data_gen.cli import main

    sys.exit(main())
except KeyboardInterrupt:  # Ctrl-C before main() took over (while importing)
    print("data_gen: interrupted", file=sys.stderr)
    sys.exit(130)
