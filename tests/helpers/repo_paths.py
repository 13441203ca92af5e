"""Where the tests find the project and the shared real data, whatever folder a test sits in."""
from pathlib import Path

#: the project root (the folder holding pyproject.toml)
REPO = Path(__file__).resolve().parents[2]
#: ``../shared/data`` beside the project: real LiDAR frames and drives (tests skip without it)
SHARED_DATA = REPO.parent / "shared" / "data"
