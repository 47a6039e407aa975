"""The network configurations a scene container carries as JSON (decoder, residual predictor), torch-free.

``decoder.py`` and ``proxy.py`` build their torch modules from these; the torch-free decode path
(``proxycodec.lite``) reads and validates a container's networks with the same classes.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

from .errors import ProxycodecError
from .render.project import GateConfig

EMBEDDINGS = ("film", "additive", "none")
#: ``DecoderConfig`` fields that describe a Scaffold-GS decoder variant (absent from JSON when at their default).
VARIANT_FIELDS = ("opacity_dist", "cov_dist", "color_dist", "feature_bank", "length_unit")
#: The near plane (scene units at ``length_unit`` 1) below which nothing is drawn.
NEAR_PLANE = 0.01


@dataclass(frozen=True)
class DecoderConfig:
    feat_dim: int = 32
    n_offsets: int = 10
    hidden: int = 32
    embedding: str = "film"  # "film" | "additive" | "none"
    film_hidden: int = 64
    pe_pos_freqs: int = 4
    pe_res_freqs: int = 4
    scene_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scene_radius: float = 1.0
    #: The resolution band the embedding was trained on; outside it the embedding sees the nearest end of the band
    #: instead of extrapolating (measured on lego: +1.2..2.6 dB at 2.5-7.5%, +0.4..2.5 dB at 120-150%).
    film_xi_range: tuple[float, float] = (0.1, 1.0)
    gate: GateConfig = field(default_factory=GateConfig)
    # Scaffold-GS's decoder variants (an imported Scaffold-GS output, ``proxycodec.scaffold_gs``); the defaults are
    # ours, and ``to_json`` leaves them out when they hold their default, so containers without them read the same.
    #: Whether the opacity / covariance / colour MLP sees the view distance (Scaffold-GS's ``add_*_dist``): its
    #: input is [f_hat, d, delta] (F + 4) or [f_hat, d] (F + 3).
    opacity_dist: bool = True
    cov_dist: bool = True
    color_dist: bool = True
    #: Hidden width of Scaffold-GS's feature bank (``use_feat_bank``: softmax(MLP([d, delta])) blends the feature
    #: with its channels at strides 4 and 2 tiled to F); 0: no feature bank.
    feature_bank: int = 0
    #: The scene's length unit relative to the units its MLPs were trained in (``convert`` trains in a canonical
    #: frame and writes the scene back in the source's units): the MLPs see the view distance divided by it and the
    #: near plane is ``NEAR_PLANE`` times it, so the scene renders the same in any units. 1 for scenes fitted as is.
    length_unit: float = 1.0

    def near_plane(self) -> float:
        return NEAR_PLANE * self.length_unit

    def __post_init__(self) -> None:
        if self.embedding not in EMBEDDINGS:
            raise ProxycodecError(f"unknown resolution embedding {self.embedding!r}; choose from {EMBEDDINGS}")
        if not (self.scene_radius > 0 and math.isfinite(self.scene_radius)):
            raise ProxycodecError(f"scene radius must be positive, got {self.scene_radius}")
        for k in ("feat_dim", "n_offsets", "hidden", "film_hidden"):
            if int(getattr(self, k)) < 1 or int(getattr(self, k)) > 4096:
                raise ProxycodecError(f"decoder {k} = {getattr(self, k)} is out of range")
        # Frequencies beyond ~20 are meaningless in float32 (2^k pi x aliases); a hostile file must not make the
        # embedding MLP's input (and its allocation) arbitrarily wide.
        for k in ("pe_pos_freqs", "pe_res_freqs"):
            if not 0 <= int(getattr(self, k)) <= 32:
                raise ProxycodecError(f"decoder {k} = {getattr(self, k)} is out of range (0..32)")
        if len(self.scene_center) != 3 or not all(math.isfinite(float(v)) for v in self.scene_center):
            raise ProxycodecError(f"scene centre must be 3 finite numbers, got {self.scene_center!r}")
        lo, hi = (float(v) for v in self.film_xi_range) if len(self.film_xi_range) == 2 else (math.nan, math.nan)
        if not (0.025 <= lo <= hi <= 2.0):
            raise ProxycodecError(f"film_xi_range must be [lo, hi] within [0.025, 2], got {self.film_xi_range!r}")
        for k in ("opacity_dist", "cov_dist", "color_dist"):
            if not isinstance(getattr(self, k), bool):
                raise ProxycodecError(f"decoder {k} must be true or false, got {getattr(self, k)!r}")
        if isinstance(self.feature_bank, bool) or not isinstance(self.feature_bank, int) \
                or not 0 <= self.feature_bank <= 4096:
            raise ProxycodecError(f"decoder feature_bank = {self.feature_bank!r} is out of range (0..4096)")
        if isinstance(self.length_unit, bool) or not (isinstance(self.length_unit, (int, float))
                                                      and math.isfinite(self.length_unit) and self.length_unit > 0):
            raise ProxycodecError(f"decoder length_unit must be a positive number, got {self.length_unit!r}")
        if self.feature_bank and self.feat_dim % 4:
            raise ProxycodecError(f"a feature bank needs a feature width divisible by 4, got {self.feat_dim}")

    def mlp_inputs(self) -> dict[str, int]:
        """Input width of the opacity / covariance / colour MLPs (by module name): F + 3 view direction + 1 distance
        where the MLP sees it."""
        F = self.feat_dim
        return {"mlp_opacity": F + 3 + self.opacity_dist, "mlp_cov": F + 3 + self.cov_dist,
                "mlp_color": F + 3 + self.color_dist}

    def variant(self) -> dict:
        """The fields that differ from a decoder fitted as is (empty for it): Scaffold-GS's variants, and
        ``length_unit`` of a converted scene. An older reader does not know them, so they raise the scene format."""
        return {k: getattr(self, k) for k in VARIANT_FIELDS
                if getattr(self, k) != DecoderConfig.__dataclass_fields__[k].default}

    def to_json(self) -> dict:
        d = asdict(self)
        d["scene_center"] = list(self.scene_center)
        d["gate"] = self.gate.to_json()
        for k in VARIANT_FIELDS:  # only where they differ: our own configurations keep their bytes
            if k not in self.variant():
                del d[k]
        return d

    @staticmethod
    def from_json(d: dict) -> "DecoderConfig":
        try:
            if not isinstance(d, dict) or not isinstance(d.get("gate", {}), dict):
                raise ProxycodecError("bad decoder configuration: expected a JSON object (with an object 'gate')")
            d = dict(d)
            gate = GateConfig.from_json(d.pop("gate", {}))
            if not all(math.isfinite(v) for v in (gate.kappa, gate.eta)):
                raise ProxycodecError("bad decoder configuration: gate kappa and eta must be finite")
            known = {f for f in DecoderConfig.__dataclass_fields__ if f != "gate"}
            kw = {k: v for k, v in d.items() if k in known}
            if "length_unit" in kw:
                kw["length_unit"] = float(kw["length_unit"])
            for k in ("scene_center", "film_xi_range"):
                if k in kw:
                    kw[k] = tuple(float(x) for x in kw[k])
            for k in ("feat_dim", "n_offsets", "hidden", "film_hidden", "pe_pos_freqs", "pe_res_freqs"):
                if k in kw:
                    kw[k] = int(kw[k])
            return DecoderConfig(gate=gate, **kw)
        except (TypeError, ValueError) as e:
            if isinstance(e, ProxycodecError):
                raise
            raise ProxycodecError(f"bad decoder configuration: {e}") from e


@dataclass(frozen=True)
class PredictorConfig:
    feat_dim: int = 32
    n_offsets: int = 10
    predict_offsets: bool = False  # also output 3K leaf-offset deltas
    hidden: int = 64
    n_blocks: int = 2
    pe_dist_freqs: int = 4
    pe_dir_freqs: int = 4
    dist_ref: float = 1.0  # distances enter as log(d / dist_ref) / 4 (dist_ref = the voxel size)
    # proxies the predictor sees: the nearest (the residual's base) and, beyond 1, the next ones as context
    # (their feature minus the nearest's, and their own distance/direction encoding)
    context: int = 1
    # how equidistant proxies are ordered (``nearest.TIES``): "grid" makes the order the predictor was trained with
    # the order every decoder finds, whatever the anchors' storage order and frame (lattice unit: dist_ref);
    # configurations written before the field existed read as "index" (``from_json``), files of the "position" rule
    # keep it, so their files decode as they always did
    ties: str = "grid"

    def __post_init__(self) -> None:
        for k in ("feat_dim", "n_offsets", "hidden"):
            if not 1 <= int(getattr(self, k)) <= 4096:
                raise ProxycodecError(f"predictor {k} = {getattr(self, k)} is out of range")
        if self.ties not in ("index", "position", "grid"):
            raise ProxycodecError(f"predictor ties = {self.ties!r}: must be 'index', 'position' or 'grid'")
        if not (math.isfinite(float(self.dist_ref)) and float(self.dist_ref) > 0):
            raise ProxycodecError(f"predictor dist_ref = {self.dist_ref!r}: must be positive")
        if not 1 <= int(self.context) <= 8:
            raise ProxycodecError(f"predictor context = {self.context} is out of range (1..8 proxies)")
        for k in ("n_blocks", "pe_dist_freqs", "pe_dir_freqs"):
            if not 0 <= int(getattr(self, k)) <= 64:
                raise ProxycodecError(f"predictor {k} = {getattr(self, k)} is out of range")
        if not (math.isfinite(self.dist_ref) and 1e-30 < self.dist_ref < 1e30):  # float32-representable
            raise ProxycodecError(f"predictor dist_ref must be positive, got {self.dist_ref}")

    @property
    def n_geo(self) -> int:
        """Width of one proxy's distance/direction encoding."""
        return (1 + 2 * self.pe_dist_freqs) + 3 * (1 + 2 * self.pe_dir_freqs)

    @property
    def n_in(self) -> int:
        return self.feat_dim + self.n_geo + (self.context - 1) * (self.feat_dim + self.n_geo)

    @property
    def n_out(self) -> int:
        return self.feat_dim + (3 * self.n_offsets if self.predict_offsets else 0)

    def to_json(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_json(d: dict) -> "PredictorConfig":
        try:
            kw = {k: d[k] for k in PredictorConfig.__dataclass_fields__ if k in d}
            for k in ("feat_dim", "n_offsets", "hidden", "n_blocks", "pe_dist_freqs", "pe_dir_freqs", "context"):
                if k in kw:
                    if isinstance(kw[k], bool) or not isinstance(kw[k], int):
                        raise ValueError(f"{k} must be an integer")
            if "predict_offsets" in kw and not isinstance(kw["predict_offsets"], bool):
                raise ValueError("predict_offsets must be a boolean")
            if "dist_ref" in kw:
                kw["dist_ref"] = float(kw["dist_ref"])
            kw.setdefault("ties", "index")  # written before the field existed
            return PredictorConfig(**kw)
        except (TypeError, ValueError, AttributeError) as e:
            if isinstance(e, ProxycodecError):
                raise
            raise ProxycodecError(f"bad predictor configuration: {e}") from None
