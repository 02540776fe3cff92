"""``motok view``: a live MuJoCo window on a motion file or a control run (docs/viewer.md).

:mod:`motok.view.playback` holds what the viewer decides (which clip and frame to show at which
wall-clock time, what a key does, where the reference's ghost goes) as plain functions, tested
without a window; :mod:`motok.view.sources` turns a motion file or a controller into clips to show;
:mod:`motok.view.window` is the thin part that opens MuJoCo's passive viewer and draws.
"""
