"""What a finished run is turned into, one module per output (``vadgs eval / render / export``).

- :mod:`~vadgs.train.results.evaluate`: test and novel-view metrics, test panels;
- :mod:`~vadgs.train.results.video`: videos (colour | depth | normals) along a camera path;
- :mod:`~vadgs.train.results.trajectory`: the camera paths of a scene: the ego path (shifted),
  through the training cameras, or an orbit (their math: :mod:`vadgs.geometry.camera_path`);
- :mod:`~vadgs.train.results.export`: the model, or the world at a frame, as a viewer-ready PLY.

Their functions are also importable from :mod:`vadgs.train`.
"""
