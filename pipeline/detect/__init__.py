"""Detectors that turn real videos into a scene's detections.

``blazepose``: Google's BlazePose models (person detector + 33-landmark model, run with a
LiteRT interpreter, the optional ``[video]`` extra), multi-person, with the pre- and
post-processing as pure functions. ``video``: reading videos and resumable detection
over a scene (``mvviz detect``).
"""
