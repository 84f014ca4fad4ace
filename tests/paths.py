"""Where things are, for tests in any folder of ``tests/``."""

from pathlib import Path

#: ``tests/``
TESTS = Path(__file__).resolve().parent
#: the repository (``tests/..``)
REPO = TESTS.parent
#: ``src/oapcal``
SRC = REPO / "src" / "oapcal"
#: test data shipped with the repository (``tests/data``)
DATA = TESTS / "data"
#: the shared real data beside the checkout (``../shared/real``); may be absent
REAL = REPO.parent / "shared" / "real"
