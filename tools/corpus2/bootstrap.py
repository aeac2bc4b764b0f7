"""Bootstrap: run the corpus2 scripts under their own virtual environment with numpy and Pillow.

`ensure()` returns when numpy and Pillow import; otherwise it creates `target/venv-corpus2` in
the repository (once), installs numpy and Pillow there with pip, and re-executes the calling
script under that interpreter. Nothing outside `target/` is touched.
"""

import os
import subprocess
import sys

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
VENV = os.path.join(REPO, "target", "venv-corpus2")
PACKAGES = ["numpy>=1.24", "Pillow>=9.0"]


def ensure():
    try:
        import numpy  # noqa: F401
        import PIL  # noqa: F401

        return
    except ImportError:
        pass
    py = os.path.join(VENV, "bin", "python")
    if os.path.abspath(sys.executable) == os.path.abspath(py):
        sys.exit(f"corpus2: {py} exists but numpy/Pillow do not import; delete {VENV} and rerun")
    if not os.path.exists(py):
        print(f"corpus2: creating {VENV} (numpy, Pillow)", file=sys.stderr)
        subprocess.check_call([sys.executable, "-m", "venv", VENV])
    subprocess.check_call([py, "-m", "pip", "install", "-q", *PACKAGES])
    os.execv(py, [py, *sys.argv])
