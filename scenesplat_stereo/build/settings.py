"""The settings of ``scenesplat-stereo build``: ``BuildSettings``, the one description of the build's flags
(each field's metadata makes its flag), checked on construction so that a refused value never reaches the
output folder; ``add_arguments`` / ``settings_from_args`` between them and argparse; ``PRESETS``, named sets
of settings (``--preset``) whose values any flag given on the command line overrides."""

from __future__ import annotations

import json
import math
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path

import torch

from scenesplat_stereo.build.effects import CameraEffects
from scenesplat_stereo.build.protocol import MIN_TEACHER_PSNR, NUM_TARGETS, TIERS
from scenesplat_stereo.common.text import (argtype, parse_counts, parse_number_or_none, parse_size, positive_number,
                                           whole_number)
from scenesplat_stereo.raster import check_device
from scenesplat_stereo.scene.teachers import OrbitSpec
from scenesplat_stereo.shards import nvjpeg
from scenesplat_stereo.shards.encode import JPEG_ENCODERS
from scenesplat_stereo.shards.encode_pool import DEFAULT_ENCODER_MODE, ENCODER_MODES, default_encoder_workers
from scenesplat_stereo.shards.sample import JPEG_QUALITY

SPLITS_OF_MODE = {"trainval": ("train", "val"), "test": ("test",)}
#: ``--preset NAME``: settings a preset sets (exactly these; a flag given on the command line wins).
#: replicags: the paper's ReplicaGS test set (appendices B and C): 100 evenly spaced reference poses per scene
#: (``--split-mode test``), all 10 targets, the teachers' native resolution (1200x680 for Replica), B = 0.10 m
#: for every scene, rho from the PSNR tiers (0.20 or 0.30 m above 35 dB), teachers above 30 dB; valid masks
#: are rendered alpha >= 0.5 in every build.
PRESETS = {
    "replicags": {"split_mode": "test", "resolution": None, "baseline": TIERS[1].baseline, "rho": None,
                  "targets": NUM_TARGETS, "min_psnr": MIN_TEACHER_PSNR, "max_frames": None},
}


def _effects(text: str, flag: str) -> str:
    CameraEffects.parse(text)  # unknown names raise, naming --effects
    return text


def _flag(help: str, **argparse_kwargs) -> dict:
    """Field metadata: the ``build`` flag of a setting (``--field-name``), its help and argparse options."""
    return {"cli": dict(help=help, **argparse_kwargs)}


def _default_device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


@dataclass(frozen=True)
class BuildSettings:
    """Everything a build needs, and the one description of the ``build`` flags (each field's metadata:
    ``add_arguments`` makes the flags from it, ``settings_from_args`` reads them back). Units:
    ``resolution`` (W, H) pixels; ``baseline``, ``rho`` world units (metres), None for the teacher's PSNR
    tier; ``min_psnr`` dB, None keeps every teacher; ``val_scenes`` {subset: k} or one k for every subset,
    None for the paper's ``VAL_SCENES``. Construction checks every value (ValueError naming the flag), so
    a refused setting never reaches the output folder."""

    teachers: Path = field(metadata=_flag(
        "folder of teacher scenes (SceneSplat-7K/gsplat, INRIA or plain layout, detected per sub-folder)",
        type=Path, required=True))
    out: Path = field(metadata=_flag(
        "output folder (OUT/<split>/shard-NNNNNN.tar, index.json, stats.json)", type=Path, required=True))
    split_mode: str = field(default="trainval", metadata=_flag(
        "trainval: train and val scene splits (seed 42), every frame for train, 5 pairs x 4 targets per val "
        "scene; test: 100 evenly spaced pairs x all targets per scene (default trainval)",
        choices=list(SPLITS_OF_MODE)))
    resolution: tuple[int, int] | None = field(default=None, metadata=_flag(
        "render size in pixels (default: each teacher's native size; K is rescaled)",
        type=argtype(parse_size, "--resolution"), metavar="WxH"))
    baseline: float | None = field(default=None, metadata=_flag(
        "stereo baseline B in world units (metres), > 0; default: PSNR tier", type=positive_number("--baseline")))
    rho: float | None = field(default=None, metadata=_flag(
        "target radius rho in world units (metres), > 0; default: PSNR tier", type=positive_number("--rho")))
    targets: int = field(default=NUM_TARGETS, metadata=_flag(
        f"targets per pair, 1..{NUM_TARGETS}: the first of the {NUM_TARGETS} Fibonacci directions (val: of the "
        "first 4)", type=whole_number("--targets")))
    val_scenes: dict[str, int] | int | None = field(default=None, metadata=_flag(
        "validation scenes per subset, e.g. 'ScanNetGS=30,ScanNetPPGS-V2=20' (the default; 0 for other "
        "subsets) or one integer for every subset", type=argtype(parse_counts, "--val-scenes"),
        metavar="SUBSET=K,...|K"))
    min_psnr: float | None = field(default=MIN_TEACHER_PSNR, metadata=_flag(
        f"keep teachers with PSNR strictly above this (dB, default {MIN_TEACHER_PSNR}); 'none' keeps all, "
        "including teachers without a PSNR", type=argtype(parse_number_or_none, "--min-psnr"), metavar="DB|none"))
    with_depth: bool = field(default=False, metadata=_flag(
        "also store the left camera's expected depth (world units along z) as float16 EXR "
        "<key>.left_depth.exr", action="store_true"))
    effects: CameraEffects | None = field(default=None, metadata=_flag(
        "camera effects on the left/right inputs only, comma-separated from noise,vignetting,exposure "
        "(default: none); --seed seeds their per-sample parameters", type=argtype(_effects, "--effects"),
        metavar="LIST"))
    device: str = field(default_factory=_default_device, metadata=_flag(
        "torch device for rendering: cpu, cuda or cuda:<n> (default: cuda when available)",
        type=argtype(check_device, "--device")))
    samples_per_shard: int = field(default=64, metadata=_flag(
        "samples (pairs) per tar shard (default 64)", type=whole_number("--samples-per-shard")))
    workers: int = field(default_factory=default_encoder_workers, metadata=_flag(
        "JPEG/PNG encoders per renderer (default: half the CPU cores; 0 encodes inline)",
        type=whole_number("--workers", 0)))
    encoder_mode: str = field(default=DEFAULT_ENCODER_MODE, metadata=_flag(
        f"threads, processes (spawned, fed through shared memory) or auto (processes on 8 or more cores, "
        f"threads under --backend ray): "
        f"the same bytes (default {DEFAULT_ENCODER_MODE}; `bench encode` compares them)", choices=list(ENCODER_MODES)))
    jpeg_encoder: str = field(default="cpu", metadata=_flag(
        "cpu: OpenImageIO/libjpeg-turbo in the encoder workers (the default, the reference bytes); nvjpeg: "
        "NVIDIA nvJPEG on the rendering GPU (needs --device cuda and the nvJPEG library; same quality and "
        "4:2:0 subsampling, other bytes: docs/benchmarks.md)", choices=list(JPEG_ENCODERS)))
    batch_pairs: int = field(default=4, metadata=_flag(
        "pairs rendered per rasterisation call (12 cameras each)", type=whole_number("--batch-pairs")))
    backend: str = field(default="local", metadata=_flag(
        "local: one process; ray: one task per teacher on an existing Ray cluster (pip extra [ray])",
        choices=["local", "ray"]))
    ray_address: str | None = field(default="auto", metadata=_flag(
        "ray.init address for --backend ray (default auto)"))
    orbit: OrbitSpec | None = field(default=None, metadata=_flag(
        "trajectory for teachers without one: 'RADIUS' or 'radius=6,frames=60,elevation=20,size=616x456,"
        "fov=60,up=-y' (world units, degrees, pixels); the orbit circles the median of the Gaussian means, "
        "OpenCV cameras looking at it", type=argtype(OrbitSpec.parse, "--orbit"), metavar="SPEC"))
    max_frames: int | None = field(default=None, metadata=_flag(
        "at most this many evenly spaced pairs per teacher (quick runs), >= 1", type=whole_number("--max-frames")))
    jpeg_quality: int = JPEG_QUALITY
    progress: bool = True

    def __post_init__(self) -> None:
        def bad(flag: str, value, why: str) -> ValueError:
            return ValueError(f"{flag} {value}: {why}")

        if self.split_mode not in SPLITS_OF_MODE:
            raise bad("--split-mode", repr(self.split_mode), f"must be one of {list(SPLITS_OF_MODE)}")
        if self.resolution is not None and (len(self.resolution) != 2 or min(self.resolution) < 1):
            raise bad("--resolution", self.resolution, "width and height must be >= 1 pixel")
        for flag, value in (("--baseline", self.baseline), ("--rho", self.rho)):
            if value is not None and not (math.isfinite(value) and value > 0):
                raise bad(flag, value, "must be a finite number > 0 (world units)")
        if not 1 <= self.targets <= NUM_TARGETS:
            raise bad("--targets", self.targets, f"must be in 1..{NUM_TARGETS}")
        for flag, value, low in (("--samples-per-shard", self.samples_per_shard, 1), ("--workers", self.workers, 0),
                                 ("--batch-pairs", self.batch_pairs, 1),
                                 ("--max-frames", 1 if self.max_frames is None else self.max_frames, 1)):
            if value < low:
                raise bad(flag, value, f"must be >= {low}")
        if not 1 <= self.jpeg_quality <= 100:
            raise bad("jpeg_quality", self.jpeg_quality, "must be in 1..100")
        if self.encoder_mode not in ENCODER_MODES:
            raise bad("--encoder-mode", repr(self.encoder_mode), f"must be one of {list(ENCODER_MODES)}")
        if self.jpeg_encoder not in JPEG_ENCODERS:
            raise bad("--jpeg-encoder", repr(self.jpeg_encoder), f"must be one of {list(JPEG_ENCODERS)}")
        if self.jpeg_encoder == "nvjpeg":
            if not str(self.device).startswith("cuda"):
                raise bad("--jpeg-encoder", "nvjpeg", f"needs a CUDA --device, got {self.device}")
            nvjpeg.load_library()  # RuntimeError naming where it looked, before anything is written
        if self.backend not in ("local", "ray"):
            raise bad("--backend", repr(self.backend), "must be 'local' or 'ray'")
        check_device(self.device)

    def fingerprint(self) -> dict:
        """The settings that decide the output bytes (stored in ``OUT/build.json``)."""
        keep = ("resolution", "baseline", "rho", "targets", "val_scenes", "min_psnr", "with_depth",
                "samples_per_shard", "max_frames", "jpeg_quality")
        doc = {k: getattr(self, k) for k in keep}
        doc["resolution"] = list(self.resolution) if self.resolution else None
        doc["teachers"] = str(Path(self.teachers).resolve())
        doc["effects"] = asdict(self.effects) if self.effects else None
        doc["orbit"] = asdict(self.orbit) if self.orbit else None
        if self.jpeg_encoder != "cpu":  # absent: the CPU encoder (as in builds from before the option)
            doc["jpeg_encoder"] = self.jpeg_encoder
        return json.loads(json.dumps(doc))


class _Default:
    """A flag's default as argparse holds it: marks a value the user did not type, which a preset replaces."""

    def __init__(self, value) -> None:
        self.value = value

    def __repr__(self) -> str:
        return repr(self.value)


def add_arguments(p) -> None:
    """The ``build`` flags, one per ``BuildSettings`` field with flag metadata, plus ``--preset``, ``--seed``
    (of the effects) and ``--no-progress``."""
    for f in fields(BuildSettings):
        if "cli" in f.metadata:
            default = {} if f.metadata["cli"].get("required") else {
                "default": _Default(f.default_factory() if f.default_factory is not MISSING else f.default)}
            p.add_argument("--" + f.name.replace("_", "-"), dest=f.name, **default, **f.metadata["cli"])
    p.add_argument("--preset", choices=sorted(PRESETS),
                   help="replicags: the paper's ReplicaGS test set: --split-mode test (100 evenly spaced pairs per "
                        "scene, 10 targets), native resolution, --baseline 0.1, rho from the PSNR tier, --min-psnr 30; "
                        "any of these flags given beside it wins (docs/dataset.md)")
    p.add_argument("--seed", type=int, default=0, help="seed of the per-sample effect parameters (default 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def settings_from_args(args) -> BuildSettings:
    """``BuildSettings`` from parsed ``build`` flags: a flag the user typed, else the ``--preset``'s value,
    else the default (ValueError naming the flag when a value is refused)."""
    preset = PRESETS[args.preset] if getattr(args, "preset", None) else {}
    values = {}
    for f in fields(BuildSettings):
        if "cli" in f.metadata:
            value = getattr(args, f.name)
            values[f.name] = preset.get(f.name, value.value) if isinstance(value, _Default) else value
    values["effects"] = CameraEffects.parse(values["effects"], args.seed)
    return BuildSettings(**values, progress=not args.no_progress)
