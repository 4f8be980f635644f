"""The capture: a phone video becomes a NeuS-layout dataset (frames, pycolmap poses, the normalised scene).

- ``frames.py``: stage 1, the video decoded into ~200 sharp, upright sRGB frames (``frames.json``);
- ``poses.py``: stage 2, pycolmap structure from motion on them;
- ``scene.py``: stage 3, the object found and put into the unit sphere (``cameras_sphere.npz``);
- ``records.py``: ``capture.json`` and ``frames.json``, the records the three stages share;
- ``run.py``: ``run_capture``, the three stages in a row, resuming after the last finished one;
- ``evaluate.py``: a capture's cameras against known ones (tests, benchmarks).

Nothing is imported here: the API checks uploads with ``frames.probe_video`` without loading pycolmap.
"""
