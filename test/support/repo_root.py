"""The repository's root directory, for the tests that read its files (README.md, doc/,
setup.py, launch/) or run a process in it."""
import os

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
