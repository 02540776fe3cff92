"""motok from Python: the main stages in memory (docs/api.md).

Load a run, generate from text, encode and decode tokens, track a motion in MuJoCo, draw it and
export it, with the library functions the ``motok`` commands call, and no file in between unless
asked for. Its names are used as ``motok.NAME`` (``motok.load_gpt``, ``motok.Motion``): the
package ``motok`` imports them from :mod:`motok.api.motion` (motions: read, write, draw,
export) and :mod:`motok.api.models` (runs: load, generate, encode, decode, track, evaluate) on
first use.
"""
