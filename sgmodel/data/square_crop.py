"""The square crop of SPEC section 7: scale a W x H sample so its short side is S, centre-crop S x S, and
move the intrinsics with it.

Pixel convention (SPEC section 1): pixel (u, v) covers [u, u+1) x [v, v+1); a continuous image coordinate
x maps to x' = s_x x - x0 under a resize by s_x followed by a crop starting at column x0, so
K' = [[s_x, 0, -x0], [0, s_y, -y0], [0, 0, 1]] K. The scaled size rounds the long side to whole pixels, so
s_x and s_y can differ by less than one pixel's worth; each axis uses its own exact factor.

Resampling: colour and other continuous images use area averaging (OpenCV ``INTER_AREA``, antialiased)
when shrinking and bilinear interpolation when enlarging; masks and depth use nearest-neighbour at pixel
centres (``INTER_NEAREST_EXACT``), so masks stay binary and depth is never mixed across edges.

Not from the paper: an image whose short side is below S / ``MAX_UPSCALE`` is refused (upsampling it by more
than 4x would train the model on interpolation blur).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

MAX_UPSCALE = 4.0  # largest accepted enlargement factor S / short side (not from the paper)


class ImageTooSmall(ValueError):
    """The image's short side is below S / MAX_UPSCALE."""


@dataclass(frozen=True)
class SquareCrop:
    """Scale (``width`` x ``height`` -> ``scaled_width`` x ``scaled_height``, short side = ``size``), then
    crop ``size`` x ``size`` starting at (``x0``, ``y0``) of the scaled image."""

    width: int
    height: int
    size: int
    scaled_width: int
    scaled_height: int
    x0: int
    y0: int

    @classmethod
    def plan(cls, width: int, height: int, size: int) -> SquareCrop:
        """The crop of a ``width`` x ``height`` image to ``size`` x ``size``; ImageTooSmall when the short
        side is below ``size / MAX_UPSCALE``."""
        if size < 1 or width < 1 or height < 1:
            raise ValueError(f"square crop: sizes must be positive, got {width}x{height} -> {size}")
        short = min(width, height)
        if short * MAX_UPSCALE < size:
            raise ImageTooSmall(f"{width}x{height} is too small for {size}x{size}: the short side must be at "
                                f"least {size}/{MAX_UPSCALE:g} = {size / MAX_UPSCALE:g} pixels")
        if width <= height:
            sw, sh = size, max(size, round(height * size / width))
        else:
            sw, sh = max(size, round(width * size / height)), size
        return cls(width, height, size, sw, sh, (sw - size) // 2, (sh - size) // 2)

    @property
    def affine(self) -> np.ndarray:
        """[3,3] float64 map from source to crop pixel coordinates (homogeneous)."""
        return np.array([[self.scaled_width / self.width, 0.0, -self.x0],
                         [0.0, self.scaled_height / self.height, -self.y0],
                         [0.0, 0.0, 1.0]])

    def intrinsics(self, K: np.ndarray) -> np.ndarray:
        """K [3,3] (pixels of the source) -> K of the crop, float64."""
        return self.affine @ np.asarray(K, dtype=np.float64)

    def _resize(self, image: np.ndarray, interpolation: int) -> np.ndarray:
        if image.shape[:2] != (self.height, self.width):
            raise ValueError(f"square crop planned for {self.width}x{self.height}, got an image of shape {image.shape}")
        scaled = image
        if (self.scaled_width, self.scaled_height) != (self.width, self.height):
            scaled = cv2.resize(image, (self.scaled_width, self.scaled_height), interpolation=interpolation)
            scaled = scaled.reshape(self.scaled_height, self.scaled_width, *image.shape[2:])
        return np.ascontiguousarray(scaled[self.y0:self.y0 + self.size, self.x0:self.x0 + self.size])

    def image(self, image: np.ndarray) -> np.ndarray:
        """A continuous image [H,W] or [H,W,C] (float32) -> [S,S(,C)]: area when shrinking, bilinear when
        enlarging."""
        shrink = self.scaled_width < self.width
        return self._resize(image, cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)

    def nearest(self, image: np.ndarray) -> np.ndarray:
        """A mask or depth map [H,W] or [H,W,C] -> [S,S(,C)], nearest pixel centre."""
        return self._resize(image, cv2.INTER_NEAREST_EXACT)
