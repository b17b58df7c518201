"""Scenes and cameras: loading NeRF-synthetic folders, instant-ngp transforms.json and COLMAP
models (``loading``, ``transforms_json``, ``colmap``, ``scene_normalisation``), the camera
models, the built-in procedural scenes, video frames, and ``process`` (photos or a video → a
posed scene through pycolmap). Imports the ops, never training or outputs."""
