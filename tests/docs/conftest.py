"""The documentation generators live in docs/gen (scripts, not a package): import them."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
GEN = ROOT / "docs" / "gen"
if str(GEN) not in sys.path:
    sys.path.insert(0, str(GEN))
