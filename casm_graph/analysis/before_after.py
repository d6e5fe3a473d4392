"""Before and after: one diagnosis against an earlier one of the same log (``diagnose --before DIAG``), per
channel and per covariate, so a user who added an effect sees which error fell and by how much."""
from __future__ import annotations

import json
from pathlib import Path

from casm_graph.io.log import LogError


def load_before(path) -> dict:
    """An earlier diagnosis: DIAG/diagnosis.json or the DIAG directory; one line on anything else."""
    p = Path(path)
    if p.is_dir():
        p = p / "diagnosis.json"
    try:
        d = json.loads(p.read_text())
    except FileNotFoundError:
        raise LogError(f"--before {path}: no diagnosis.json there") from None
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise LogError(f"--before {p}: not a diagnosis.json ({type(exc).__name__})") from None
    if not isinstance(d, dict) or not isinstance(d.get("channels"), dict) or "verdict" not in d:
        raise LogError(f"--before {p}: not a diagnosis.json (no 'channels' and 'verdict')")
    return d


def _covariate(rec: dict, name: str, kind: str) -> float | None:
    for c in rec.get("covariates", []):
        if c.get("name") == name and c.get("kind", kind) == kind:
            return c.get("strength")
    for c in rec.get("covariates", []):         # the same covariate tested for the other kind
        if c.get("name") == name:
            return c.get("strength")
    return None


def compare(before: dict, after: dict) -> dict:
    """What changed from ``before`` to ``after`` (both diagnosis.json dicts).

    Per channel: the whitened and raw residual RMS, and the strongest covariate of the earlier diagnosis
    with its strength (omega squared) then and now; the open-loop prediction error per horizon then and
    now (``predictive``, when both diagnoses have it). Log-likelihoods are the refitted models' on the same
    log and sightings; they compare when the same sightings were set aside (both counts are given).
    """
    chans = {}
    for ch in sorted(set(before["channels"]) | set(after["channels"])):
        b, a = before["channels"].get(ch, {}), after["channels"].get(ch, {})
        top = (b.get("covariates") or [{}])[0]
        row = {"rms": [b.get("rms"), a.get("rms")], "rms_raw": [b.get("rms_raw"), a.get("rms_raw")]}
        if top.get("name"):
            row["covariate"] = {"name": top["name"], "kind": top.get("kind", "mean"),
                                "strength": [top.get("strength"), _covariate(a, top["name"], top.get("kind", "mean"))]}
        chans[ch] = row
    bb, ab = before.get("base", {}), after.get("base", {})
    pb, pa = before.get("predictive") or {}, after.get("predictive") or {}
    pred = {}
    if pb.get("horizons_s") and pb.get("horizons_s") == pa.get("horizons_s"):
        common = sorted(set(pb.get("channels", {})) & set(pa.get("channels", {})))
        pred = {"horizons_s": pa["horizons_s"], "channels": {ch: [pb["channels"][ch], pa["channels"][ch]] for ch in common}}
    return {**({"predictive": pred} if pred else {}),"verdict": [before.get("verdict"), after.get("verdict")],
            "effects": [sorted(bb.get("effects", {})), sorted(ab.get("effects", {}))],
            "log_likelihood": [bb.get("log_likelihood"), ab.get("log_likelihood")],
            "sightings_set_aside": [before.get("sightings_set_aside", 0), after.get("sightings_set_aside", 0)],
            "channels": chans}
