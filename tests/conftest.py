import os

os.environ.setdefault("WARP_LOG_LEVEL", "error")
