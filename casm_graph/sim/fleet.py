"""A simulated fleet: many robots, one log a day each, some of them wearing out.

``simulate_fleet(OUT)`` writes ``OUT/robotNN/2026-03-DD/`` log bundles (each with ``meta.json``
``{"robot", "time"}`` and its ``truth_model.json``) and ``OUT/fleet_truth.json``: which robots wear,
and every robot's true velocity scale and camera gain on every day.

How robots differ and wear, with the public simulator only (``cg.simulate`` and its ``extra_effects``
option, which takes user :class:`casm_graph.Effect` classes):

* **Own table.** The Aibo simulator draws its true table from the seed (the attempted velocities with
  per-action quirks), so the table of robot r is the one drawn from the robot's seed. Each day's log
  uses its own seed (new path, new noise), and a motion effect ``fleet_table`` maps every row of that
  day's drawn table to the same row of the robot's table times the day's velocity scale. The effect
  is the only motion effect, so the simulator hands it exactly a row of the day's table.
* **Own camera.** A sensor effect ``fleet_camera`` multiplies the beacon height by the robot's gain
  (about 1 +- 4 %), which is a pinhole camera with ``focal_px`` times the gain: truth_model.json says so.
* **Wear.** ``wearing`` robots (chosen by ``seed``) lose ``wear_per_day`` of every velocity per day:
  on day d (0 the first) their table is scaled by 1 - wear_per_day * d. The others keep scale 1.

truth_model.json of every bundle holds the robot's true (scaled) table and camera, so reports compare
the fit with what that robot really did; the two helper effects are not in its ``effects`` (they are
no physics the fit should look for) but under ``fleet``.
"""
from __future__ import annotations

import json
import warnings

import numpy as np

from casm_graph.io.log import LogError
from casm_graph.io.output import atomic_dir, checked_out, json_text
from casm_graph.models.effects import Effect
from casm_graph.sim.protocols import simulate, write_log

SCHEMA = "casm-graph/fleet-truth/1"
START_DATE = (2026, 3, 1)
CAMERA_GAIN_SD = 0.04


def robot_seed(seed: int, robot: int, day: int | None = None) -> int:
    """A seed for robot ``robot`` (its table) or for its log on ``day`` (its path and noise)."""
    key = [int(seed), int(robot)] + ([] if day is None else [int(day) + 1])
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def drawn_table(seed: int) -> np.ndarray:
    """The (A, 3) true table the Aibo simulator draws from ``seed`` (from a short simulation's truth)."""
    for minutes in (0.2, 1.0, 5.0):         # the table is the seed's first draw, whatever the length; a run
        try:                                 # too short to see any beacon has no truth to read it from
            with warnings.catch_warnings():  # few distances seen: the truth's cubic is ill-posed, no matter here
                warnings.simplefilter("ignore")
                _, truth = simulate("aibo", minutes=minutes, seed=seed)
            break
        except ValueError:
            continue
    vel = truth["action_model"]["velocities"]
    return np.array([vel[str(a)] for a in range(len(vel))], float)


def table_effect(drawn: np.ndarray, robot_table: np.ndarray) -> type[Effect]:
    """A motion effect that runs the robot's table (times its parameter) whenever the simulator runs ``drawn``."""
    lookup = {row.tobytes(): robot_table[i] for i, row in enumerate(np.ascontiguousarray(drawn, float))}

    def velocity(self, theta, v, ctx):
        rows = []
        for row in np.ascontiguousarray(v, float):
            hit = lookup.get(row.tobytes())
            if hit is None:
                raise RuntimeError("fleet_table: the simulator ran a velocity that is no row of its drawn table")
            rows.append(hit)
        return np.array(rows) * theta[0]

    return type("FleetTable", (Effect,), {"name": "fleet_table", "channel": "motion", "params": ("scale",),
                                          "physics": "this robot's own table, scaled by its wear",
                                          "velocity": velocity})


class FleetCamera(Effect):
    """Sensor effect: this robot's camera reads ``gain`` times the standard camera's beacon height."""

    name = "fleet_camera"
    channel = "sensor"
    params = ("gain",)
    physics = "this robot's own camera gain"

    def reading(self, theta, predicted, ctx):
        return predicted * theta[0]


def date(day: int) -> str:
    y, m, d = START_DATE
    return f"{y:04d}-{m:02d}-{d + day:02d}"


def simulate_fleet(out, robots: int = 20, days: int = 5, minutes: float = 3.0, seed: int = 0, wearing: int = 2,
                   kind: str = "aibo", wear_per_day: float = 0.04, force: bool = False) -> dict:
    """Write the fleet's bundles under ``out`` (all or nothing) and return fleet_truth.json's content."""
    if kind != "aibo":
        raise LogError(f"simulate-fleet: kind {kind!r} is not supported: only 'aibo' logs can carry a robot's own "
                       f"table and its wear (the floor simulator has no command-map scale option yet)")
    if robots < 1 or days < 1:
        raise LogError(f"simulate-fleet: --robots and --days must be at least 1 (got {robots}, {days})")
    if days > 28:
        raise LogError(f"simulate-fleet: --days at most 28 (one log a day from {date(0)}; got {days})")
    if not 0 <= wearing <= robots:
        raise LogError(f"simulate-fleet: --wearing must be between 0 and --robots ({robots}); got {wearing}")
    if not 0 <= wear_per_day * (days - 1) < 1:
        raise LogError(f"simulate-fleet: wear {wear_per_day:g} per day over {days} days would stop the robot")
    if minutes <= 0:
        raise LogError(f"simulate-fleet: --minutes must be positive (got {minutes:g})")
    checked_out(out, force)
    rng = np.random.default_rng([int(seed), 99])
    worn = sorted(int(r) for r in rng.choice(robots, size=wearing, replace=False))
    gains = 1.0 + CAMERA_GAIN_SD * rng.standard_normal(robots)
    truth = {"schema": SCHEMA, "kind": kind, "robots": robots, "days": days, "minutes": minutes, "seed": seed,
             "wear_per_day": wear_per_day,
             "wearing": [f"robot{r:02d}" for r in worn],
             "how": "every velocity of a wearing robot's table is scaled by 1 - wear_per_day * day (day 0 the first)",
             "robot": {}}
    with atomic_dir(out, force=force) as tmp:
        for r in range(robots):
            name = f"robot{r:02d}"
            own = drawn_table(robot_seed(seed, r))
            entry = {"table_seed": robot_seed(seed, r), "camera_gain": float(gains[r]), "wearing": r in worn,
                     "sessions": []}
            for d in range(days):
                s = robot_seed(seed, r, d)
                scale = 1.0 - wear_per_day * d if r in worn else 1.0
                log, tr = simulate("aibo", minutes=minutes, seed=s,
                                   effects={"fleet_table": scale, "fleet_camera": float(gains[r])},
                                   extra_effects=(table_effect(drawn_table(s), own), FleetCamera))
                tr = _robot_truth(tr, own * scale, float(gains[r]), name, d, scale)
                where = tmp / name / date(d)
                write_log(log, where, tr)
                (where / "meta.json").write_text(json.dumps({"robot": name, "time": date(d)}) + "\n")
                entry["sessions"].append({"time": date(d), "path": f"{name}/{date(d)}", "seed": s,
                                          "velocity_scale": scale})
            truth["robot"][name] = entry
        (tmp / "fleet_truth.json").write_text(json_text(truth))
    return truth


def _robot_truth(tr: dict, table: np.ndarray, gain: float, robot: str, day: int, scale: float) -> dict:
    """truth_model.json of one session: the robot's scaled table and its camera (focal length times the gain)."""
    tr = json.loads(json.dumps(tr))
    tr["action_model"]["velocities"] = {str(a): v.tolist() for a, v in enumerate(table)}
    sm = tr["sensor_model"]
    sm["camera"]["focal_px"] *= gain
    sm["reading_poly_best_cubic"] = [c * gain for c in sm["reading_poly_best_cubic"]]
    tr["effects"] = {}
    tr["simulation"]["effects"] = {}
    tr["fleet"] = {"robot": robot, "day": day, "velocity_scale": scale, "camera_gain": gain,
                   "mechanism": "casm_graph.sim.fleet: the robot's own table and camera gain"}
    return tr
