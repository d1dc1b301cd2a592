"""Where the tests find the real LWA capture files (``$BF_EPIC_DATA``, else ``../shared/data/lwa``)."""
import os
from pathlib import Path


def _data_dir() -> Path:
    env = os.environ.get("BF_EPIC_DATA")
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data" / "lwa"


DATA = _data_dir()
SV = DATA / "lwasv-adp-tbf.dat"
NA = DATA / "lwana-ndp-tbf.dat"
