"""ament_pep257 over the package's own source, as ROS's ament_python template runs it."""

from pathlib import Path

from ament_pep257.main import main
import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = ['mlv_ros', 'test', 'bench', 'launch', 'setup.py', 'scripts', 'fuzz', 'bags']
# Rules the docstrings do not meet yet (issue 18 item 7): a hand-written one-line summary (D205,
# D400, D415), an imperative one (D401), argument descriptions (D417). Drop a code here once
# `ament_pep257` reports none of it; every other rule of ament's convention holds.
PENDING = ['D205', 'D400', 'D401', 'D415', 'D417']


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257():
    rc = main(argv=[*(str(REPO / s) for s in SOURCES), '--add-ignore', *PENDING])
    assert rc == 0, 'Found code style errors / warnings'
