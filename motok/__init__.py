"""motok: learned human motion, from mocap to tokens, text and physics.

``import motok`` is quick and loads neither torch nor MuJoCo: each name of the Python API
(:mod:`motok.api`, docs/api.md), e.g. ``motok.load_gpt``, is imported the first time it is used.
"""

__version__ = "0.2.0"

# Each name of the Python API and the module of motok.api that defines it (its __all__).
API = {name: "motion" for name in ("Motion", "export_bvh", "load_motions", "render_frames", "render_motion",
                                   "save_motions")}
API.update({name: "models" for name in ("TaskPolicy", "TrackResult", "decode", "encode", "evaluate_task",
                                        "generate", "load", "load_controller", "load_gpt", "load_policy",
                                        "load_tokenizer", "track")})


def __getattr__(name: str):
    if name in API:
        # Imported by name, on first use. An import statement here would read as a circle to the
        # static import check (tests/test_imports.py: the API imports every stage and every stage
        # imports this package), but none runs: this runs after the stages are loaded, and no module
        # of motok takes an API name from `motok` (tests/test_api.py checks both).
        import importlib

        return getattr(importlib.import_module(f"motok.api.{API[name]}"), name)
    raise AttributeError(f"module 'motok' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(API))
