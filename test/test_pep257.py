"""ament_pep257 over the package's own source, as ROS's ament_python template runs it."""

from pathlib import Path

from ament_pep257.main import main
import pytest

REPO = Path(__file__).resolve().parents[1]
SOURCES = ['mlv_ros', 'test', 'bench', 'launch', 'setup.py', 'scripts', 'fuzz', 'bags']


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257():
    """Check the docstrings against ament's convention, nothing skipped."""
    rc = main(argv=[str(REPO / s) for s in SOURCES])
    assert rc == 0, 'Found code style errors / warnings'
