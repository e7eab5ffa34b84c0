"""The lab: what happens after milling.

From a video to tracks (video -> scene -> camera -> ball finder -> track):

video.py       decoding videos with PyAV: grey frames and their presentation times
scene.py       the still scene: a sample of the frames, the ArUco markers in it, the background and its noise
camera.py      the markers' layout on the top face, the camera calibrated from their corners, a pixel's ray
               met with the ball-centre offset surface
ballfinder.py  the ball's centre in each frame from its silhouette (shadows rejected, its sigma), or a gap's reason
track.py       a video tracked: VideoTrack (CSV, JSON), track_video, the review sheet

From tracks to a fitted spec (tracks -> events -> fits -> outcomes -> loss laws -> summary):

tracks.py      readers of tracked trajectories (Tracker, CSV, trackpy) and the video-to-design map
events.py      segmentation and events: what a track shows before any model fit
fitting.py     the fitting machinery: bounded least-squares fits of the model to tracks
track_fits.py  each track's fits: the model's start and viscous damping
outcome.py     the outcome of each launch
losses.py      the loss laws the tracks support
analyze.py     the analysis of tracked launches and releases, running the stages above
summary.py     what a person reads of an analysis

ramp.py        the launch ramp as a watertight solid with calibrated release marks
"""
