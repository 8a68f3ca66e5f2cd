"""`python -m services.planner`: the planner without the tether CLI, settings from the environment."""

from __future__ import annotations

import sys
from pathlib import Path

from services.planner.main import main
from services.runtime import NodeSettings

if __name__ == "__main__":
    main(NodeSettings.from_env(), Path(sys.argv[1]) if len(sys.argv) > 1 else None)
