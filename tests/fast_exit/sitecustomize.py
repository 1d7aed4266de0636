"""Imported by every Python interpreter the tests start (conftest.py puts this folder on their PYTHONPATH): at exit,
the interpreter's final searches for reference cycles skip the objects still alive (gc.freeze); objects are still
freed as their last references go. With torch imported those searches take 1-3 s a process on a CI machine, and the
suite starts about 170 interpreters."""

import atexit
import gc

atexit.register(gc.freeze)
