"""Optional camera effects on the stereo inputs: exposure jitter, vignetting and sensor noise.

The paper renders clean images (appendix B); these effects are an option of ours for training encoders
that must cope with real sensors, and every one is off unless ``--effects`` names it. They apply to the
two *input* cameras (left and right) only: targets are the supervision and stay clean renders of the
teacher, and valid masks come from rendered alpha, untouched.

Per sample (one reference pose), with parameters drawn from a generator seeded by (seed, key), so the
same seed and key always give the same images on a given device:

- exposure: a gain 2^ev, ev uniform in +-``EXPOSURE_EV_RANGE``; the right camera's ev differs from the
  left's by a uniform +-``EXPOSURE_PAIR_MISMATCH_EV`` (two sensors, nominally matched). The result is
  clipped at 1 (saturation).
- vignetting: natural cos^4 fall-off raised to a strength s uniform in ``VIGNETTING_STRENGTH``:
  gain(u, v) = cos(theta)^(4 s), cos(theta) = 1 / sqrt(1 + ((u+0.5-cx)/fx)^2 + ((v+0.5-cy)/fy)^2),
  the same lens for both cameras.
- noise: Poisson-Gaussian sensor noise in its Gaussian approximation, x + sqrt(a x + b^2) n with n
  standard normal per pixel and channel; shot gain a log-uniform in ``NOISE_SHOT_GAIN``, read noise b
  uniform in ``NOISE_READ_STD``; an independent draw per camera.

Values are in the rendered [0, 1] range; the caller rounds to uint8 afterwards. With no effect on,
``CameraEffects.parse`` returns None and the build never calls into this module (the no-op path).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import torch

EFFECT_NAMES = ("noise", "vignetting", "exposure")

# Our choices, not the paper's (the paper renders without effects).
EXPOSURE_EV_RANGE = 0.5  # +- stops, per sample
EXPOSURE_PAIR_MISMATCH_EV = 0.05  # +- stops, right camera relative to left
VIGNETTING_STRENGTH = (0.5, 1.5)  # exponent s on the cos^4 law
NOISE_SHOT_GAIN = (1e-4, 4e-3)  # a, log-uniform; variance a * x
NOISE_READ_STD = (0.002, 0.01)  # b, uniform; standard deviation in [0, 1] units


def _rng(seed: int, key: str) -> np.random.Generator:
    digest = hashlib.sha256(f"{int(seed)}\x00{key}".encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:16], "little"))


@dataclass(frozen=True)
class SampleEffects:
    """The effect parameters of one sample: ``ev`` [2] stops (left, right), ``vignetting`` strength s,
    noise ``shot_gain`` a and ``read_std`` b, and ``noise_seeds`` [2] for the per-camera noise draws.
    A parameter of an effect that is off is neutral (0 stops, s = 0, a = b = 0)."""

    ev: tuple[float, float]
    vignetting: float
    shot_gain: float
    read_std: float
    noise_seeds: tuple[int, int]


@dataclass(frozen=True)
class CameraEffects:
    """Which effects are on, and the seed of their per-sample parameters."""

    noise: bool = False
    vignetting: bool = False
    exposure: bool = False
    seed: int = 0

    @classmethod
    def parse(cls, text: str | None, seed: int = 0) -> CameraEffects | None:
        """``"noise,vignetting,exposure"`` (any subset, comma-separated; "" or "none" for none) -> the
        effects, or None when none is on. Unknown names raise ValueError naming them."""
        names = [t.strip().lower() for t in (text or "").split(",") if t.strip()]
        if names == ["none"]:
            names = []
        unknown = sorted(set(names) - set(EFFECT_NAMES))
        if unknown:
            raise ValueError(f"--effects: unknown effect(s) {unknown}; choose from {', '.join(EFFECT_NAMES)}")
        if not names:
            return None
        return cls(noise="noise" in names, vignetting="vignetting" in names, exposure="exposure" in names,
                   seed=int(seed))

    @property
    def names(self) -> list[str]:
        return [n for n in EFFECT_NAMES if getattr(self, n)]

    def sample(self, key: str) -> SampleEffects:
        """The parameters of sample ``key`` (deterministic in (seed, key)). All draws are made whatever is
        on, so turning one effect on or off does not change the others' parameters."""
        rng = _rng(self.seed, key)
        ev = rng.uniform(-EXPOSURE_EV_RANGE, EXPOSURE_EV_RANGE)
        mismatch = rng.uniform(-EXPOSURE_PAIR_MISMATCH_EV, EXPOSURE_PAIR_MISMATCH_EV)
        strength = rng.uniform(*VIGNETTING_STRENGTH)
        shot = float(np.exp(rng.uniform(np.log(NOISE_SHOT_GAIN[0]), np.log(NOISE_SHOT_GAIN[1]))))
        read = rng.uniform(*NOISE_READ_STD)
        seeds = rng.integers(0, 2**62, size=2)
        return SampleEffects(
            ev=(float(ev), float(ev + mismatch)) if self.exposure else (0.0, 0.0),
            vignetting=float(strength) if self.vignetting else 0.0,
            shot_gain=shot if self.noise else 0.0,
            read_std=float(read) if self.noise else 0.0,
            noise_seeds=(int(seeds[0]), int(seeds[1])),
        )

    def apply(self, stereo: torch.Tensor, keys: list[str], Ks: torch.Tensor) -> torch.Tensor:
        """Apply the effects to stereo inputs ``stereo`` [P, 2, H, W, 3] (left, right; values in [0, 1])
        of P samples named ``keys``, with intrinsics ``Ks`` [P, 3, 3] (pixels; left and right share them).
        Returns a new tensor of the same shape, on the same device."""
        if stereo.ndim != 5 or stereo.shape[1] != 2 or stereo.shape[0] != len(keys):
            raise ValueError(f"CameraEffects.apply: expected [P={len(keys)}, 2, H, W, C], got {list(stereo.shape)}")
        p, _, h, w, _ = stereo.shape
        out = torch.empty_like(stereo)
        for i, key in enumerate(keys):
            params = self.sample(key)
            img = stereo[i]
            if self.exposure:
                gain = torch.tensor([2.0**e for e in params.ev], dtype=img.dtype, device=img.device)
                img = (img * gain.view(2, 1, 1, 1)).clamp(max=1.0)
            if self.vignetting:
                img = img * _vignette(Ks[i], w, h, params.vignetting, img.device, img.dtype)[None, :, :, None]
            if self.noise:
                noisy = []
                for cam in range(2):
                    gen = torch.Generator(device=img.device).manual_seed(params.noise_seeds[cam])
                    n = torch.randn(img[cam].shape, generator=gen, device=img.device, dtype=img.dtype)
                    std = torch.sqrt(params.shot_gain * img[cam].clamp(min=0.0) + params.read_std**2)
                    noisy.append(img[cam] + std * n)
                img = torch.stack(noisy)
            out[i] = img
        return out


def _vignette(K: torch.Tensor, width: int, height: int, strength: float, device, dtype) -> torch.Tensor:
    """cos(theta)^(4 s) over the pixel centres [H, W] of a pinhole camera K (pixels)."""
    K = K.to(device=device, dtype=torch.float64)
    u = (torch.arange(width, device=device, dtype=torch.float64) + 0.5 - K[0, 2]) / K[0, 0]
    v = (torch.arange(height, device=device, dtype=torch.float64) + 0.5 - K[1, 2]) / K[1, 1]
    r2 = v[:, None] ** 2 + u[None, :] ** 2
    return ((1.0 + r2) ** (-2.0 * strength)).to(dtype)
