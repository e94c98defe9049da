import subprocess
import sys

import pytest

import psmini


@pytest.mark.slow
def test_import_loads_the_core_only():
    """DESIGN: the core depends on torch, numpy and kornia; files, the rig and the CLI sit around it."""
    code = "import sys, psmini; print(','.join(m for m in ('cv2', 'plyfile', 'serial', 'skimage') if m in sys.modules))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == ""


def test_all_names_exist():
    missing = [name for name in psmini.__all__ if not hasattr(psmini, name)]
    assert missing == []
