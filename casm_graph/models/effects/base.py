"""The shape of an effect: a physical process the base model lacks, with its parameters and its change.

An effect is a small class. It names its parameters and their starting values, says in one
sentence what physics it stands for, which residual covariate it should explain, whether a log
can support it, and changes one thing: the velocity a step really runs (``velocity``), where
the sensor and landmark are when an observation is taken (``geometry``), the predicted reading
(``reading``), or the noise (``reading_scale``, ``outlier_fraction``). Hooks left alone change
nothing. The simulator applies the same hooks with the true parameters, and the factor graph
(:mod:`casm_graph.graph.augmented`) with the parameters as variables, differentiating the hooks
numerically: an effect is written as its forward physics only.

Context arrays (one row per step or observation) handed to the hooks:

* motion ``ctx``: ``t`` (s since the log began), ``pose`` (n, 3) at the step's start, ``since``
  (s since the current action began), ``dt``, ``v_prev`` (n, 3) velocity of the action before it;
* sensor ``ctx``: ``t``, ``pose`` (n, 3), ``landmark`` (row index), ``pan`` (n,; NaN when not
  logged), ``velocity`` (n, 3) body velocity at the observation, ``image_angle`` (n,) predicted.
"""
from __future__ import annotations

import numpy as np

from casm_graph.io.log import Log, LogError

REGISTRY: dict[str, type["Effect"]] = {}
_ORDERED: dict[tuple, type["Effect"]] = {}     # (family's class, order) -> its member, made once


class Effect:
    """Base class: override the class attributes and the hooks your physics changes."""

    name: str = ""
    channel: str = "motion"                 # "motion" or "sensor" (INTERFACE section 6)
    params: tuple[str, ...] = ()
    start: tuple[float, ...] = ()           # starting values of the parameters in a fit
    scale: tuple[float, ...] = ()           # typical magnitudes (finite-difference steps, priors)
    explains: tuple[tuple[str, str], ...] = ()   # (channel, covariate) residual structure it accounts for
    physics: str = ""                       # one sentence for the catalog and the diagnosis
    distinguished_by: str = ""              # what in a log tells it from the effects it resembles (look-alikes)
    signature: str = "covariates"           # the diagnosis report's view that shows its trace: "covariates" (the residuals
                                            # against what it ``explains``), "correlation" (against the commands' changes
                                            # over time), "field" (over the floor), "speed" (the motion achieved over
                                            # time), "landmarks" or "tails" (the sightings' residual distribution)
    noise_only: bool = False                # parameters set by the noise step, not least squares
    continuous_only: bool = False           # needs continuous (v, w) commands: the action-table simulator refuses it
    uses_velocity: bool = False             # its sensor hooks read ctx["velocity"] (the body velocity at the sighting)
    map_bound: bool = False                 # its hooks read where the robot is or which way it faces on the map (a field
                                            # over the floor): a fit may not move the map's frame under it
    scale_free: bool = False                # no parameter holds a length (a delay, a share, an image angle): the map may be
                                            # scaled under it, the action model and sensor curve following
    velocity_window: str = ""               # the parameter (s) over which that velocity is averaged before the sighting
                                            # on continuous commands (empty: the step that ends at the sighting)
    orders: tuple[int, ...] = ()            # a family's complexities, compared by BIC in a diagnosis (empty: one form)
    order: int | None = None                # this class's complexity among ``orders``
    prior_widths: tuple[float, ...] = (1.0,)  # multiples of ``prior``'s sigma every action-table fit freeing it tries
                                            # (a calibration, a diagnosis's candidate and folds), keeping the fit of
                                            # highest likelihood (a loose prior lets many parameters wander where the
                                            # data hardly pin them, a tight one holds a large effect back)
    prior_width: float = 1.0                # the multiple this instance's prior is taken at

    def __init__(self, log: Log | None = None, order: int | None = None):
        self.log = log
        if order is not None or self.order is not None:
            self.set_order(self.order if order is None else order)

    def __reduce__(self):
        """An instance travels to a worker process as its class's :func:`spec` (a family member's class is made on
        demand, so it goes by ``name:order``) and its attributes as they are."""
        return _rebuilt, (spec(type(self)), self.__dict__)

    @classmethod
    def of_order(cls, order: int) -> type["Effect"]:
        """The family member of complexity ``order`` (one class per order, so a name travels as ``name:order``)."""
        _check_order(cls, order)
        root = REGISTRY.get(cls.name, cls)
        if root.order == order:
            return root
        key = (root, order)
        if key not in _ORDERED:
            _ORDERED[key] = type(root.__name__, (root,), {"order": order, "__doc__": root.__doc__,
                                                                 "__module__": root.__module__})
        return _ORDERED[key]

    def set_order(self, order: int) -> None:
        """Shape the parameters for complexity ``order`` (a family overrides this; see ``orders``)."""
        _check_order(self, order)
        self.order = order

    def begin(self, model, poses: np.ndarray) -> None:
        """Called before a fit starts this effect from nothing, with ``poses`` (T+1, 3) of a fit of ``model`` without
        it: an effect whose start depends on the log (a patch's edges) sets ``self.start`` here."""

    # ----------------------------------------------------------------- support
    def applicable(self, log: Log) -> str | None:
        """None when ``log`` can support this effect, else the reason it cannot."""
        return None

    def free_parameters(self) -> int:
        """Parameters the data must pin down (BIC counts these)."""
        return len(self.params)

    def prior(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(mean, sigma) of a Gaussian prior on the parameters, or None for none."""
        return None

    def implausible(self, theta: np.ndarray) -> str | None:
        """None when ``theta`` describes physics that can happen, else why not (a floor that makes the robot several
        times faster): such a fit fits something else, and a diagnosis keeps it out of its verdict."""
        return None

    def reframe(self, theta: np.ndarray, scale: bool = False) -> np.ndarray | None:
        """After a fit: an effect whose parameters leave the map's frame free (moving every landmark together)
        chooses it, keeps it, and returns the similarity (phi, tx, ty, s) the poses make with it, s = 1 unless
        ``scale`` (every effect of the model ``scale_free``); None: no such freedom."""
        return None

    def simulate_params(self, value: float, rng: np.random.Generator) -> np.ndarray:
        """True parameters for ``simulate --effect NAME=VALUE``."""
        return np.array([value], float)

    def describe(self, theta: np.ndarray) -> dict:
        return {**{p: float(v) for p, v in zip(self.params, theta)}, **({"order": self.order} if self.orders else {}),
                **self.described_width()}

    def described_width(self) -> dict:
        """The prior's width for a model.json entry where it is not the prior itself (a calibration chose it)."""
        return {"prior_width": float(self.prior_width)} if self.prior_width != 1.0 else {}

    def theta_of(self, entry: dict) -> np.ndarray:
        """The parameters a model.json ``entry`` records (its start where one is absent), after taking back what
        else it records (:meth:`restore`)."""
        self.restore(entry)
        return np.array([float(entry.get(p, s)) for p, s in zip(self.params, self.start)])

    def restore(self, entry: dict) -> None:
        """Take back what ``describe`` recorded beside the parameters from a model.json entry: a family's order
        (its parameters follow), the prior's width, and in a subclass what else it records (a field's extent)."""
        if self.orders and entry.get("order") is not None:
            self.set_order(int(entry["order"]))
        if entry.get("prior_width") is not None:
            self.prior_width = float(entry["prior_width"])

    # ------------------------------------------------------------------- hooks
    def velocity(self, theta: np.ndarray, v: np.ndarray, ctx: dict) -> np.ndarray:
        """(n, 3) body velocity each step really runs, given the table's ``v``."""
        return v

    def geometry(self, theta, pose, landmark_xy, ctx) -> tuple[np.ndarray, np.ndarray]:
        """Sensor pose and landmark position an observation really sees."""
        return pose, landmark_xy

    def reading(self, theta: np.ndarray, predicted: np.ndarray, ctx: dict) -> np.ndarray:
        """The reading the sensor reports, given the polynomial's prediction."""
        return predicted

    def reading_scale(self, theta: np.ndarray, distance: np.ndarray, ctx: dict) -> np.ndarray:
        """Factor on the reading noise sigma of each observation."""
        return np.ones_like(distance)

    def outlier_fraction(self, theta: np.ndarray) -> float:
        """Share of observations that belong to no landmark the model knows."""
        return 0.0

    @property
    def mixture(self) -> bool:
        """Whether the effect is an outlier mixture (it has an :meth:`outlier_fraction` of its own)."""
        return type(self).outlier_fraction is not Effect.outlier_fraction

    def estimate_noise(self, theta, reading_z, bearing_z, distance, ctx) -> np.ndarray:
        """New noise parameters from whitened reading and bearing residuals (noise-only effects)."""
        return theta

    def corrupt(self, theta, obs: dict, rng: np.random.Generator) -> dict:
        """Simulator: change the observation arrays after they are drawn (e.g. mislabel some)."""
        return obs


def _check_order(effect, order) -> None:
    if order not in effect.orders:
        raise LogError(f"effect {effect.name!r}: order {order} is not one of its forms "
                       f"({', '.join(map(str, effect.orders)) or 'it has one form'})")


def held(cls: type[Effect]) -> type[Effect]:
    """``cls`` with its parameters held where they are: least squares and the noise step leave them alone."""
    return type(cls.__name__, (cls,), {"noise_only": True, "estimate_noise": Effect.estimate_noise,
                                      "__doc__": f"{cls.__name__} with its parameters held fixed."})


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator adding an effect to the registry under its ``name``."""
    if not cls.name:
        raise ValueError("an effect needs a name")
    REGISTRY[cls.name] = cls
    return cls


def get(name: str) -> type[Effect]:
    """The catalog class named ``name``, or ``name:order`` for a family member of that complexity."""
    base, sep, order = name.partition(":")
    if base not in REGISTRY:
        raise LogError(f"unknown effect {base!r} (known: {', '.join(sorted(REGISTRY))})")
    if not sep:
        return REGISTRY[base]
    try:
        k = int(order)
    except ValueError:
        raise LogError(f"effect {name!r}: the order after ':' must be a whole number") from None
    return REGISTRY[base].of_order(k)


def _rebuilt(kind, state: dict) -> Effect:
    """An effect instance from :meth:`Effect.__reduce__`: the class of ``kind`` (a spec or a class), ``state`` its
    attributes."""
    cls = get(kind) if isinstance(kind, str) else kind
    out = cls.__new__(cls)
    out.__dict__.update(state)
    return out


def unphysical(cls: type[Effect], entry: dict, log: Log | None = None) -> str | None:
    """Why the model.json ``entry`` of effect class ``cls`` (``describe``'s output) cannot happen, or None
    (:meth:`Effect.implausible`)."""
    if cls.implausible is Effect.implausible:        # every fit of it can happen (a region's list of levels, ...)
        return None
    eff = cls(log)
    return eff.implausible(eff.theta_of(entry))


def spec(cls: type[Effect]):
    """How ``cls`` travels to a worker process: its catalog name (``name:order`` for a family member), which
    :func:`get` turns back into it, or the class itself (a user's effect)."""
    root = REGISTRY.get(cls.name)
    if root is cls:
        return cls.name
    if root is not None and cls.order is not None and _ORDERED.get((root, cls.order)) is cls:
        return f"{cls.name}:{cls.order}"
    return cls
