"""The SLAM core: local VO (``vo``), global Sim(3) graph (``graph``), depth sources, loop closure.

Pure library: no zenoh, FastAPI, httpx or torch imports (a test enforces it).
"""
