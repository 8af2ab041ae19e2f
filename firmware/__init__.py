# upright firmware package (MicroPython >= 1.22; also imports under CPython).
# Nothing runs at import time: the application starts in main.py.
