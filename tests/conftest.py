import os

os.environ.setdefault("MAVLINK20", "1")
