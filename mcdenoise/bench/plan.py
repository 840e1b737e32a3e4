"""What ``mcdenoise bench`` measures: methods, sizes, sample counts, and the time budget.

A *method* is a registered model at one preset (``wskp:paper``) or OIDN at one quality
(``oidn:high``). An *entry* is a method at one size and, for sample models, one spp. Entries of one
``(size, spp)`` group are timed round-robin in the same rounds; OIDN, the pixel models and the
sample models at :data:`ANCHOR_SPP` share one group per size, so every model's ratio to OIDN
comes from the same rounds. The first (smallest) size runs every entry; larger sizes run the
entries whose time, extrapolated from the measured ones by pixel count, fits the budget, most
important first (OIDN and the issue's targets always). Skipped entries are reported with their
estimate.

A model with shipped weights is also timed through the public API (``mcdenoise.denoise`` with
numpy arrays and ``model=`` its weights), as the method ``NAME:PRESET api`` in the same rounds as
its bare model call: the difference is what a user pays beyond the network (loading, channel
checks, tiling plan, conversions). Such an entry is planned like its model's but never forced in
(it is not a target).
"""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = [
    "Method", "BenchConfig", "TARGETS", "ANCHOR_SPP", "DEFAULT_METHODS", "QUICK_METHODS",
    "parse_method", "default_methods", "quick_config", "full_config", "priority",
]

#: The spp of the group that holds OIDN and the pixel models (the issue's targets are at 8 spp).
ANCHOR_SPP = 8

#: Issue 12's CPU targets: (method label, spp or None, limit of time / OIDN high time at 1920x1080).
TARGETS: tuple[tuple[str, int | None, float], ...] = (
    ("wskp:paper", None, 0.25),
    ("kpcn:small", None, 1.0),
    ("layer_optimized:paper_timed", 8, 2.0),
    ("layer_optimized:small", 8, 2.0),
    ("sbmc:small", 8, 10.0),
    # Issue 20: the combiner's own cost (OIDN's output is its input), so the whole path is <= 1.5x.
    ("combine:small", None, 0.5),
    ("combine:ens", None, 0.5),
    ("combine:own", None, 0.5),
    ("combine:ens_kpcn", None, 0.5),
    ("combine:kpcn", None, 0.5),
)

#: Beyond every registered model's ``small`` preset: the presets the papers' timings and the
#: issue's targets name (WSKP is timed as published; the layer paper's timed U-Net size; the
#: combiner inside issue 20's 1.5x).
EXTRA_METHODS: tuple[str, ...] = ("wskp:paper", "wskp:paper3", "layer_optimized:paper_timed", "combine:own")

DEFAULT_METHODS = ("oidn:high", "oidn:fast")

#: ``--quick``: OIDN and the four target models' small presets plus WSKP's paper preset.
QUICK_METHODS: tuple[str, ...] = ("oidn:high", "oidn:fast", "wskp:paper", "kpcn:small", "layer_optimized:small",
                                  "sbmc:small", "combine:small")


@dataclass(frozen=True)
class Method:
    """A model preset or an OIDN quality."""

    name: str
    """Registered model name, or ``oidn``."""
    preset: str
    """Model preset, or OIDN quality (``high``, ``fast``)."""
    api: bool = False
    """Timed through ``mcdenoise.denoise`` with the shipped weights, not as a bare model call."""

    @property
    def label(self) -> str:
        return f"{self.name}:{self.preset}" + (" api" if self.api else "")

    @property
    def bare(self) -> "Method":
        """The same model as a bare call (itself when not an API entry)."""
        return Method(self.name, self.preset)

    @property
    def is_oidn(self) -> bool:
        return self.name == "oidn"


def parse_method(text: str) -> Method:
    """``"wskp"`` (small preset), ``"wskp:paper"``, ``"oidn"`` (high) or ``"oidn:fast"``."""
    name, _, preset = text.partition(":")
    if not name:
        raise ValueError(f"bad method {text!r}: expected NAME or NAME:PRESET")
    return Method(name, preset or ("high" if name == "oidn" else "small"))


def default_methods() -> list[Method]:
    """OIDN high and fast, every registered model's ``small`` preset, and :data:`EXTRA_METHODS`."""
    from mcdenoise.models.registry import list_models

    labels = [*DEFAULT_METHODS, *(f"{e.name}:small" for e in list_models()), *EXTRA_METHODS]
    return [parse_method(t) for t in dict.fromkeys(labels)]


@dataclass
class BenchConfig:
    """Settings of one ``mcdenoise bench`` run."""

    methods: list[Method] = field(default_factory=list)
    """Methods to measure (empty: :func:`default_methods`)."""
    sizes: tuple[tuple[int, int], ...] = ((256, 256), (1280, 720), (1920, 1080))
    """Image sizes ``(width, height)``, smallest first (the first size calibrates the budget)."""
    spp: tuple[int, ...] = (1, 4, 8, 16, 32)
    """Samples per pixel for sample models (pixel models and OIDN get pixel means)."""
    warmup: int = 2
    """Untimed calls per entry before timing (the first one also measures peak memory). Two: at
    1080p the first two calls of a model are 1.5-2x slower than the rest (fresh 2 MiB pages);
    an entry whose first call exceeds ``slow_s`` stops warming up after it."""
    rounds: int = 3
    """Timed rounds; each entry's figure is the median over rounds."""
    slow_s: float = 8.0
    """At sizes after the first, an entry whose warm-up call took longer than this gets one timed
    round (still in the same round as OIDN) instead of ``rounds``: a 1080p SBMC call is tens of
    seconds, and its spread between rounds is small next to that."""
    budget_s: float = 300.0
    """Estimated seconds of timed work allowed for the sizes after the first (OIDN and targets
    run whatever their estimate, and their estimate counts against it)."""
    target_size: tuple[int, int] = (1920, 1080)
    """Size at which the issue's target entries always run (elsewhere they share the budget)."""
    memory_fraction: float = 0.4
    """Skip an entry whose inputs would exceed this fraction of the available memory."""
    device: str = "cpu"
    oidn_threads: int | None = None
    """Threads of OIDN's CPU device (``bench --threads N`` sets torch's and this alike); None:
    every core (OIDN's default)."""
    fast: bool = True
    """Fast inference paths (:mod:`mcdenoise.models.inference`); False times the reference."""
    precision: str = "auto"
    """Convolution trunks in ``float32``, ``bfloat16``, or ``auto`` (bfloat16 where the device
    computes it natively; see :func:`mcdenoise.models.inference.resolve_precision`). The test-split
    metrics of each precision are in docs/PERFORMANCE.md."""
    train_batch: int = 8
    """Crops per training step for the throughput figure (``mcdenoise train``'s default)."""
    train_crop: int = 48
    train_spp: int = 8
    train_steps: int = 3
    """Timed training steps per model (after one untimed); 0 skips training throughput."""
    api: bool = True
    """Also time the public API path (:func:`mcdenoise.denoise`) of every model with shipped
    weights, beside its bare call (see the module docstring)."""
    peak_conv: tuple[int, int] = (128, 128)
    """Channels and image side of the convolution that measures the machine's peak GFLOP/s."""
    seed: int = 0


def quick_config(**overrides: object) -> BenchConfig:
    """``--quick``: 256x256 only, 1 and 8 spp, two rounds, a two-step training figure."""
    cfg = BenchConfig(methods=[parse_method(t) for t in QUICK_METHODS], sizes=((256, 256),), spp=(1, 8), rounds=2, warmup=1,
                      train_batch=4, train_crop=32, train_steps=1, peak_conv=(64, 128))
    for k, v in overrides.items():
        setattr(cfg, k, v)
    return cfg


def full_config(**overrides: object) -> BenchConfig:
    cfg = BenchConfig()
    for k, v in overrides.items():
        setattr(cfg, k, v)
    return cfg


#: Entries always run at 1280x720 too: WSKP's paper times 720p (Table 3).
PAPER_720P: tuple[str, ...] = ("wskp:paper", "wskp:paper3")


def priority(method: Method, spp: int | None, size: tuple[int, int] | None = None,
             target_size: tuple[int, int] = (1920, 1080)) -> int:
    """Lower runs first and is never dropped for time when 0: OIDN at every size, the issue's
    targets at ``target_size`` (or at any size when ``size`` is None), WSKP's paper presets at 720p."""
    if method.is_oidn:
        return 0
    if method.api:  # beside its model, but never forced in for time
        return max(1, priority(method.bare, spp, size, target_size))
    if (size is None or size == target_size) and any(method.label == t and (s is None or s == spp) for t, s, _ in TARGETS):
        return 0
    if size == (1280, 720) and method.label in PAPER_720P:
        return 0
    if spp is None or spp == ANCHOR_SPP:
        return 1
    return 2
