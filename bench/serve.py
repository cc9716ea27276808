"""Live-session load benchmark; same as ``facecast bench serve`` (see facecast.server.bench.serve)."""

import sys

from facecast.server.bench.serve import main

if __name__ == "__main__":
    sys.exit(main())
