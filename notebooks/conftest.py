"""Notebooks run in the test command (nbmake) at smoke-test sizes, writing to a temp folder."""
import os
import tempfile

os.environ.setdefault("COMGS_NOTEBOOK_TINY", "1")
os.environ.setdefault("COMGS_NOTEBOOK_OUT", tempfile.mkdtemp(prefix="comgs_notebooks_"))
os.environ.setdefault("MPLBACKEND", "Agg")
