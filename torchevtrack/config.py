"""Tracker configuration: nested dataclasses, loadable from YAML.

The dataclass defaults are the reference; :data:`DEFAULT_YAML` (``torchevtrack/configs/default.yaml``, shipped
in the package as a starting point to copy) spells them out and a test keeps the two equal.
A YAML file may give any subset of keys; unknown keys are errors.

Example:
    >>> from torchevtrack.config import TrackerConfig
    >>> cfg = TrackerConfig.from_dict({"rate_hz": 250, "ukf": {"enabled": False}})
    >>> cfg.rate_hz, cfg.ukf.enabled, cfg.eros.kernel_size
    (250.0, False, 7)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from torchevtrack.mesh import check_decimate
from torchevtrack.render import BACKENDS

__all__ = [
    "ErosConfig",
    "FlowConfig",
    "VelocityConfig",
    "TemplateConfig",
    "UKFConfig",
    "RenderConfig",
    "LossConfig",
    "BurstConfig",
    "DenoiseConfig",
    "RecoverConfig",
    "HypothesesConfig",
    "TrackerConfig",
    "ABLATIONS",
    "DEFAULT_YAML",
]

RULES = ("argmax", "group", "newton")  # template.rule: the correction's decision rules
TWIST_AXES = ("vx", "vy", "vz", "wx", "wy", "wz")  # names of the twist components [v, w]
DEFAULT_YAML = Path(__file__).parent / "configs" / "default.yaml"  # every key with its default value


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader that refuses a key given twice in one mapping (plain YAML keeps the last silently)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"key {key!r} given twice", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


RECENCY_STEP_US = 250  # a recency window that follows the image speed is a multiple of this


def recency_windows(recency_us: float, px: float, min_us: float, max_us: float) -> tuple[float, ...]:
    """The recency windows an element may take (microseconds, :class:`~torchevtrack.stages.eros.Recency`): just
    ``recency_us`` if fixed (``px == 0``, or ``recency_us == 0``: no weighting, so nothing to follow), else the
    multiples of :data:`RECENCY_STEP_US` from ``min_us`` to ``max_us``, which must be such multiples, with
    ``recency_us`` one of them. Raises ValueError otherwise."""
    if not (px >= 0 and recency_us >= 0):
        raise ValueError(f"the recency window and its px must be >= 0, got {recency_us} us, {px} px")
    if px == 0 or recency_us == 0:
        return (float(recency_us),)
    step = RECENCY_STEP_US
    if not 0 < min_us <= recency_us <= max_us or any(v % step for v in (min_us, max_us, recency_us)):
        raise ValueError(f"a recency window that follows the speed needs min_us <= recency_us <= max_us, positive "
                         f"multiples of {step} us, got {min_us}, {recency_us}, {max_us}")
    return tuple(float(v) for v in range(int(min_us), int(max_us) + 1, step))


@dataclass
class ErosConfig:
    kernel_size: int = 7  # odd window size k
    decay: float = 0.3  # d; the per-event factor is d ** (1 / k)
    max_age_us: int = 30_000  # > 0: the observation drops pixels with no event for this long (0 = the paper)
    recency_us: float = 2500.0  # > 0: the observation weighs pixels by exp(-age / recency_us) (0 = the paper)
    recency_px: float = 2.5  # > 0: recency_us (the first window) follows the image speed: the time edges take to
    # move this far (0 = fixed at recency_us; ignored with recency_us 0)
    recency_min_us: float = 1250.0  # the bounds of a recency that follows the speed (multiples of 250 us)
    recency_max_us: float = 5000.0


@dataclass
class FlowConfig:
    block: int = 20  # grid RoI size, pixels
    min_samples: int = 10  # triplet samples a block needs to yield a flow vector
    radius: int = 2  # D: triplet offsets |dx|, |dy| <= D
    dt_max_us: int = 50_000
    tol: float = 0.125
    onset_us: int = 0  # > 0: only a crossing's first event is matched, one whose pixel was silent this long (0 = all)
    max_speed: float = 5000.0  # px/s; faster block flows are discarded as outliers (degenerate fits)
    estimate: str = "normal"  # "normal" (time-surface gradient fit of the inliers) or "register" (the paper)


@dataclass
class VelocityConfig:
    source: str = "flow"  # "flow" (the paper), "poses" (EDOPT_Vel: from consecutive poses) or "none"
    rho: float = 0.75  # velocity decay per update (paper: 0.5; 0.75 holds more dev runs: docs/notebook.md, 2026-11-28)
    # pitch and yaw rates' decay in a steady turn, reached as the rotation keeps its direction over the running means
    # of the rate (turn_ema per update); rho_turn = rho: one decay (stages.velocity.turn_decay; notebook 2026-12-02)
    rho_turn: float = 0.9
    turn_ema: float = 0.04
    q_v: float = 0.5  # process noise std of the centre velocity per update, m/s
    q_w: float = 3.0  # process noise std of w per update, rad/s
    r_px: float = 0.2  # measurement noise floor per flow vector, pixels of displacement per update
    # plus this fraction of its own displacement, in quadrature (notebook 2026-12-01; 0.3 until 2026-12-02 late)
    r_rel: float = 0.2
    min_vectors: int = 3
    # width of the robust (Laplacian) weights of the flow vectors, in robust standard deviations of their residuals
    # (stages.velocity.kf_update's k)
    robust_k: float = 0.5  # 1.0 before (docs/notebook.md, 2026-12-02 late)
    # Correction feedback (stages.velocity.CorrectionFeedback): a leaky integral of the template corrections'
    # rate, bounded by feedback_max_v (m/s) / feedback_max_w (rad/s), is added to the flow twist on the axes the
    # flow hardly observes; gain 0 = off (the paper).
    feedback_gain: float = 0.2
    feedback_leak: float = 0.8
    feedback_axes: list[str] = field(default_factory=lambda: ["vz", "wx", "wy"])
    feedback_max_v: float = 0.1
    feedback_max_w: float = 0.5


@dataclass
class TemplateConfig:
    enabled: bool = True
    canvas: int = 128
    margin_px: int = 20
    dp_px: float = 1.0
    dtheta_deg: float = 1.0
    rule: str = "newton"  # "newton" (all axes, sub-step), "argmax" (the paper) or "group" (EDOPT)
    iterations: int = 5  # correction rounds per update while the score improves (1 = the paper)
    warmup_events: int = 2000  # events an element must have seen since reset before its pose is corrected
    interior: float = 0.7  # weight of the object's coverage added to the edge template, with its area term (0: edges)
    # m/s: per update a correction's depth stays within this times the period of the last measured depth moved on by
    # the prediction (.inf: no bound)
    max_depth_speed: float = 2.5


@dataclass
class UKFConfig:
    # the paper's step 6 in the loop: off by default, it held fewer runs on fresh dev data (docs/method.md)
    enabled: bool = False
    q_pdot: float = 1.0  # process noise densities: (m/s)^2/s
    q_w: float = 10.0  # (rad/s)^2/s
    q_p: float = 1e-4  # m^2/s
    q_q: float = 1e-3  # rad^2/s
    r_p: float = 1e-5  # measurement variances: m^2
    r_q: float = 1e-4  # rad^2
    p0: float = 1e-3  # initial variance of every tangent component


@dataclass
class RenderConfig:
    decimate: int | None = None  # faces of the hot-path mesh (None = full mesh)
    margin_px: int = 24  # region rendered around the projected object
    # Render each update's template at the pose the previous update predicted for it (its prediction moved on by
    # its twist for one period) instead of at the new prediction; the Newton search starts at the new prediction
    # all the same. With the pipeline, that render then runs on the intake thread during the previous update.
    ahead: bool = True
    backend: str = "raster"  # "raster" (compiled CPU z-buffer, 3-5x faster on the tracker's windows) or "pyrender" (OpenGL)


@dataclass
class LossConfig:
    # Tracking-loss detection (torchevtrack.loss.LossDetector); it only reports, unless an on_lost callback
    # (or the user's masked reset) re-initialises the lost elements.
    enabled: bool = False
    score_threshold: float = 0.6  # low update: template score below this fraction of the running reference
    min_flow_vectors: int = 3  # low update: fewer flow vectors (not applied unless velocity.source = "flow")
    patience: int = 25  # consecutive low updates that declare an element lost
    recovery: int = 10  # consecutive confident updates that clear it
    ema: float = 0.05  # rate of the reference score's moving average


@dataclass
class BurstConfig:
    # Burst guard (torchevtrack.stages.burst.BurstGuard): a window holding more events than min_fraction of the
    # sensor's pixels and more than ratio times the recent rate (an EMA of weight ema) is a burst (a flash, a bump);
    # its events reach no stage, the velocity filter only predicts, the loss detector takes it as neutral. After
    # max_run consecutive bursts the next window is accepted as the new normal.
    enabled: bool = True
    min_fraction: float = 0.05
    ratio: float = 10.0
    ema: float = 0.05
    max_run: int = 25


@dataclass
class DenoiseConfig:
    # Background-activity and hot-pixel filter (torchevtrack.stages.denoise.BackgroundActivityFilter), applied after
    # the burst guard: an event passes when a 3x3 neighbour fired at most dt_us before it and its pixel is not hot.
    enabled: bool = False
    dt_us: int = 10_000
    hot_period_us: int = 200_000
    hot_ratio: float = 8.0
    hot_min_rate_hz: float = 50.0


@dataclass
class RecoverConfig:
    # Re-localisation (torchevtrack.recover.Recoverer; needs loss.enabled). While an element the loss detector
    # declares lost keeps tracking (its output flagged lost), a wide search
    # (torchevtrack.stages.relocalise.Relocaliser), centred on its last good pose moved on by its last good twist,
    # runs at the declaration, retry_us of event time later, then at doubling intervals (up to
    # torchevtrack.recover.MAX_RETRY_US), once min_events pixels fired within the last retry_us beside another that
    # did (isolated noise does not count); where that search finds nothing, a second one centred where a scan of the
    # whole frame puts the object (out of view and back, or far after a blackout); the element restarts at a clear
    # result that beats its own pose, or is found again where the search confirms that pose.
    # start_search: one such search start_after_us after each (re)start, from the tracker's pose then; it restarts
    # the element where its result costs 1 px less than both the runner-up and the tracker's pose
    # (torchevtrack.recover.beats_start, START_MARGIN_PX; no max_cost_px). search_m: the search's image-plane
    # half-width (metres at the object's depth; its depth offsets scale with it); the search blocks the update (~0.3-1.5
    # s of wall time).
    # max_cost_px: a result is clear (restarts the element) at a chamfer cost of at most this many pixels (and a
    # runner-up 0.5 px worse): after a blackout the object's recent edges are smeared, and found poses cost 1.6-4 px,
    # 4.4-4.7 px at 1280x720 with sensor noise.
    # check_us: every this much event time an element that is not lost is checked against its depth rivals (its pose
    # 20 % nearer and 25 % farther, torchevtrack.stages.relocalise.Relocaliser.rivals); one that costs check_margin_px
    # less flags it drifted (a depth drift the template score does not show), in the lost flags; reported only, no
    # search; 0: no check.
    enabled: bool = False
    retry_us: int = 20_000
    min_events: int = 500
    search_m: float = 0.10
    start_search: bool = False
    start_after_us: int = 48_000
    max_cost_px: float = 5.0
    check_us: int = 50_000
    check_margin_px: float = 0.5


@dataclass
class HypothesesConfig:
    # Two hypotheses per object (torchevtrack.hypotheses): the tracker keeps a twin of itself with the UKF off, fed
    # the same events; every period_us of event time the two poses' chamfer costs against the same recent events are
    # compared, and after patience checks in a row in which one costs less than the other divided by ratio, it is the
    # output and the other takes its motion state. About 2.3x the time of one tracker (docs/benchmarks.md).
    enabled: bool = False
    ratio: float = 1.5
    patience: int = 2
    period_us: int = 20_000


@dataclass
class TrackerConfig:
    rate_hz: float = 500.0
    eros: ErosConfig = field(default_factory=ErosConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    velocity: VelocityConfig = field(default_factory=VelocityConfig)
    template: TemplateConfig = field(default_factory=TemplateConfig)
    ukf: UKFConfig = field(default_factory=UKFConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    burst: BurstConfig = field(default_factory=BurstConfig)
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)
    recover: RecoverConfig = field(default_factory=RecoverConfig)
    hypotheses: HypothesesConfig = field(default_factory=HypothesesConfig)

    def __post_init__(self) -> None:
        self.rate_hz = float(self.rate_hz)
        if self.rate_hz <= 0:
            raise ValueError(f"rate_hz must be positive, got {self.rate_hz}")
        if self.eros.recency_us < 0 or self.eros.max_age_us < 0:
            raise ValueError("eros.max_age_us and eros.recency_us must be >= 0 (0 = off)")
        e = self.eros
        try:
            recency_windows(e.recency_us, e.recency_px, e.recency_min_us, e.recency_max_us)
        except ValueError as err:
            raise ValueError(f"eros.recency_*: {err}") from None
        if isinstance(self.flow.onset_us, bool) or not isinstance(self.flow.onset_us, int) or self.flow.onset_us < 0:
            raise ValueError(f"flow.onset_us must be an int >= 0 (0 = off), got {self.flow.onset_us!r}")
        if self.velocity.source not in ("flow", "poses", "none"):
            raise ValueError(f"velocity.source must be 'flow', 'poses' or 'none', got {self.velocity.source!r}")
        v = self.velocity
        if not v.feedback_gain >= 0 or not 0 <= v.feedback_leak < 1 or not isinstance(v.feedback_axes, list) \
                or any(a not in TWIST_AXES for a in v.feedback_axes) or not v.feedback_max_v > 0 \
                or not v.feedback_max_w > 0:
            raise ValueError(f"velocity.feedback_gain must be >= 0, feedback_leak in [0, 1), feedback_axes a list of "
                             f"{TWIST_AXES} and feedback_max_v, feedback_max_w positive, got {v.feedback_gain!r}, "
                             f"{v.feedback_leak!r}, {v.feedback_axes!r}, {v.feedback_max_v!r}, {v.feedback_max_w!r}")
        if self.template.rule not in RULES:
            raise ValueError(f"template.rule must be one of {RULES}, got {self.template.rule!r}")
        if not (math.isfinite(self.template.interior) and self.template.interior >= 0):
            raise ValueError(f"template.interior must be finite and >= 0, got {self.template.interior!r}")
        m = self.template.max_depth_speed
        if isinstance(m, bool) or not isinstance(m, (int, float)) or not m > 0:
            raise ValueError(f"template.max_depth_speed must be > 0 m/s (.inf: no bound), got {m!r}")
        if self.render.backend not in BACKENDS:
            raise ValueError(f"render.backend must be one of {BACKENDS}, got {self.render.backend!r}")
        check_decimate(self.render.decimate, "render.decimate")
        r = self.recover
        if r.enabled and not self.loss.enabled:
            raise ValueError("recover.enabled needs the loss detector: set loss.enabled")
        if r.start_search and not r.enabled:
            raise ValueError("recover.start_search needs recover.enabled")
        if r.retry_us <= 0 or r.min_events < 0 or not r.search_m > 0 or r.start_after_us <= 0 or not r.max_cost_px > 0:
            raise ValueError(f"recover.retry_us and start_after_us must be positive, min_events >= 0, search_m and "
                             f"max_cost_px > 0, got {r.retry_us!r}, {r.start_after_us!r}, {r.min_events!r}, "
                             f"{r.search_m!r}, {r.max_cost_px!r}")
        h = self.hypotheses
        if h.enabled and not (self.ukf.enabled and self.template.enabled):
            raise ValueError("hypotheses.enabled needs ukf.enabled and template.enabled: its twin is the tracker "
                             "without the UKF, judged by the rendered model")
        if not h.ratio > 1 or h.patience < 1 or h.period_us <= 0:
            raise ValueError(f"hypotheses.ratio must be > 1, patience >= 1 and period_us > 0, got {h.ratio!r}, "
                             f"{h.patience!r}, {h.period_us!r}")

    @property
    def period_us(self) -> int:
        return round(1e6 / self.rate_hz)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrackerConfig":
        return _build(cls, d, "config")

    @classmethod
    def from_yaml(cls, path: str | Path) -> "TrackerConfig":
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"config file not found: {path}")
        try:
            d = yaml.load(path.read_text(), Loader=_UniqueKeyLoader) or {}
        except yaml.YAMLError as e:
            raise ValueError(f"{path}: {' '.join(str(e).split())}") from None
        if not isinstance(d, dict):
            raise ValueError(f"{path}: expected a mapping at the top level")
        return _build(cls, d, str(path))

    def override(self, assignments: list[str]) -> "TrackerConfig":
        """A copy with single settings changed by ``"dotted.key=value"`` strings (the CLI's ``--set``).

        Each value is read as YAML and must fit the type the schema gives its key: ``int``, ``float`` (an
        integer is accepted), ``bool`` (``true`` / ``false``), ``str``, ``list[str]`` (``[a, b]`` or ``a,b``),
        ``None`` where the key allows it (``null``). Later assignments win. Raises ``ValueError`` with a
        one-line message on a malformed assignment, an unknown key or a value of the wrong type.

        Example:
            >>> cfg = TrackerConfig().override(["ukf.enabled=false", "rate_hz=250", "velocity.feedback_axes=vz,wx"])
            >>> cfg.ukf.enabled, cfg.rate_hz, cfg.velocity.feedback_axes
            (False, 250.0, ['vz', 'wx'])
        """
        d = self.to_dict()
        for text in assignments:
            key, sep, raw = str(text).partition("=")
            key = key.strip()
            if not sep or not key:
                raise ValueError(f"--set expects KEY=VALUE (e.g. ukf.enabled=false), got {text!r}")
            cls, section, parts = TrackerConfig, d, key.split(".")
            for i, name in enumerate(parts):
                fields = {f.name: f for f in dataclasses.fields(cls)}
                where = ".".join(parts[:i]) or "the config"
                if name not in fields:
                    raise ValueError(f"unknown config key {key!r}: {where} has {', '.join(sorted(fields))}")
                sub = fields[name].default_factory
                nested = sub is not dataclasses.MISSING and dataclasses.is_dataclass(sub)
                if i < len(parts) - 1:
                    if not nested:
                        raise ValueError(f"unknown config key {key!r}: {'.'.join(parts[:i + 1])} is not a section")
                    cls, section = sub, section[name]
                elif nested:
                    raise ValueError(f"config key {key!r} is a section: set one of its keys, e.g. {key}."
                                     f"{dataclasses.fields(sub)[0].name}=...")
                else:
                    section[name] = _typed(key, raw.strip(), _field_type(cls, name))
        return TrackerConfig.from_dict(d)

    def replace(self, **changes: dict) -> "TrackerConfig":
        """A copy with some sections changed, e.g. ``cfg.replace(ukf={"enabled": False})``."""
        d = self.to_dict()
        for k, v in changes.items():
            d[k] = {**d[k], **v} if isinstance(v, dict) else v
        return TrackerConfig.from_dict(d)


def _field_type(cls, name: str) -> str:
    """The annotation of field ``name`` of dataclass ``cls``, as written in the source (e.g. ``"int | None"``)."""
    ann = next(f.type for f in dataclasses.fields(cls) if f.name == name)
    return ann if isinstance(ann, str) else getattr(ann, "__name__", str(ann))


def _typed(key: str, raw: str, ann: str):
    """``raw`` read as YAML and checked against the annotation ``ann`` (int, float, bool, str, list[str], X | None)."""
    try:
        value = yaml.safe_load(raw) if raw else None
    except yaml.YAMLError:
        value = raw
    if isinstance(value, str):  # YAML 1.1 reads 1e-3 as text; Python reads it as a number
        for number in (int, float):
            try:
                value = number(raw)
                break
            except ValueError:
                pass
    kinds = [k.strip() for k in ann.split("|")]
    if value is None and "None" in kinds:
        return None
    for kind in kinds:
        if kind == "bool" and isinstance(value, bool):
            return value
        if kind == "int" and isinstance(value, int) and not isinstance(value, bool):
            return value
        if kind == "float" and isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if kind == "str" and isinstance(value, str):
            return value
        if kind == "str" and isinstance(value, (int, float)) and not isinstance(value, bool):
            return raw  # a name that reads as a number stays the text given
        if kind == "list[str]":
            items = value if isinstance(value, list) else [s.strip() for s in raw.strip("[]").split(",") if s.strip()]
            if all(isinstance(v, str) for v in items):
                return items
    raise ValueError(f"config key {key!r} expects {ann}, got {raw!r}")


def _build(cls, d: dict, where: str):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(d) - set(fields)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {sorted(unknown)}; known: {sorted(fields)}")
    kwargs = {}
    for name, value in d.items():
        f = fields[name]
        sub = f.default_factory if f.default_factory is not dataclasses.MISSING else None
        if sub is not None and dataclasses.is_dataclass(sub):
            if not isinstance(value, dict):
                raise ValueError(f"{where}: section {name!r} must be a mapping")
            kwargs[name] = _build(sub, value, f"{where}.{name}")
        else:
            kwargs[name] = value
    return cls(**kwargs)


# The paper's methods as config changes (Table I rows; each names its UKF, so it is the same whatever the default),
# and the full method with its twin without the UKF (torchevtrack.hypotheses). The default config is ``no_ukf``.
_UKF, _NO_UKF = {"enabled": True}, {"enabled": False}
ABLATIONS: dict[str, dict] = {
    "full": {"ukf": _UKF},
    "no_ukf": {"ukf": _NO_UKF},
    "velocity_only": {"template": {"enabled": False}, "ukf": _UKF},
    "correction_only": {"velocity": {"source": "none"}, "ukf": _UKF},
    "edopt_vel": {"velocity": {"source": "poses"}, "ukf": _UKF},
    "hypotheses": {"hypotheses": {"enabled": True}, "ukf": _UKF},
}
