"""The lab: what happens after milling.

tracks.py   readers of tracked trajectories (Tracker, CSV, trackpy) and the video-to-design map
analyze.py  events (bounces, outcome, entry and exit speeds) and model fits of tracked launches
ramp.py     the launch ramp as a watertight solid with calibrated release marks
"""
