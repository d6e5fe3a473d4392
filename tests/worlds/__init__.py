"""Test worlds written apart from casm_graph (numpy only), each writing a log bundle with its truth."""
from tests.worlds import independent_world, omni_world


def generate_world(kind: str, out_dir, minutes: float, seed: int, effect: str | None = None, **options) -> dict:
    """Write the bundle of a world of ``kind`` ("omni": the omnidirectional robot; else the independent world's kind,
    "table" or "continuous", ``options`` its own) into ``out_dir``; the truth dict, the effect's strength as
    ``strength`` either way."""
    if kind == "omni":
        truth = omni_world.generate(out_dir, minutes=minutes, seed=seed, effect=effect, **options)
        return {**truth, "strength": truth["effect"]["strength"]}
    return independent_world.generate(out_dir, kind=kind, minutes=minutes, seed=seed, effect=effect, **options)
