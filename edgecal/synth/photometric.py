"""From linear radiance to an 8-bit camera image: light, optics blur, response, noise, quantisation.

The order follows the physics: the light falling on the scene (gradient, vignetting) multiplies the
albedo, the lens blurs the result, the sensor response maps it to digital numbers (black and white
level, gamma), noise is added, and the value is rounded to uint8 (optionally JPEG-compressed). None of
these steps moves a corner: they are point-symmetric or smooth over the size of a corner, so the
geometric ground truth holds for every setting.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Photometric:
    """Photometric settings of one render (all optional; the default is a clean, sharp image).

    blur_sigma:   Gaussian optics blur, px.
    gradient:     illumination change (gx, gy) from the image centre to the right / bottom edge (fraction).
    vignetting:   fractional darkening at the image corners (1 - v r^2, r = 1 at a corner).
    black_level, white_level: digital numbers for radiance 0 and 1 (contrast).
    gamma:        sensor encoding: DN ∝ radiance^(1/gamma).
    noise_sigma:  additive Gaussian noise, DN.
    jpeg_quality: None, or the JPEG quality (1..100) the image goes through.
    """

    blur_sigma: float = 0.0
    gradient: tuple[float, float] = (0.0, 0.0)
    vignetting: float = 0.0
    black_level: float = 0.0
    white_level: float = 255.0
    gamma: float = 1.0
    noise_sigma: float = 0.0
    jpeg_quality: int | None = None

    def as_json(self) -> dict:
        """Plain JSON values, for the ``render.photometric`` section of the truth file."""
        d = asdict(self)
        d["gradient"] = [float(v) for v in self.gradient]
        return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in d.items()}


CLEAN = Photometric()


def illumination(size: tuple[int, int], gradient: tuple[float, float], vignetting: float) -> np.ndarray:
    """Relative illumination (h, w) float32: a linear gradient times a radial fall-off."""
    w, h = size
    xn = (np.arange(w, dtype=np.float32) - (w - 1) / 2.0) / (w / 2.0)
    yn = (np.arange(h, dtype=np.float32) - (h - 1) / 2.0) / (h / 2.0)
    light = np.add.outer(np.float32(gradient[1]) * yn, np.float32(1.0) + np.float32(gradient[0]) * xn)
    if vignetting:
        v = np.float32(0.5 * vignetting)
        light *= np.add.outer(-v * yn * yn, np.float32(1.0) - v * xn * xn)
    return np.maximum(light, np.float32(0.05))


def apply_photometric(radiance: np.ndarray, params: Photometric, rng: np.random.Generator) -> np.ndarray:
    """The uint8 image a camera would record of ``radiance`` (h, w) float in [0, 1] under ``params``."""
    img: np.ndarray = np.asarray(radiance, dtype=np.float32)
    h, w = img.shape
    if params.gradient != (0.0, 0.0) or params.vignetting:
        img = img * illumination((w, h), params.gradient, params.vignetting)
    if params.blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), float(params.blur_sigma), borderType=cv2.BORDER_REFLECT)
    img = np.clip(img, 0.0, 1.0)
    if params.gamma != 1.0:
        img = img ** np.float32(1.0 / params.gamma)
    dn = np.float32(params.black_level) + np.float32(params.white_level - params.black_level) * img
    if params.noise_sigma > 0:
        dn = dn + rng.standard_normal((h, w), dtype=np.float32) * np.float32(params.noise_sigma)
    out = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
    if params.jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(params.jpeg_quality)])
        if ok:
            out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return out


def random_photometric(rng: np.random.Generator, level: str = "normal") -> Photometric:
    """Random settings: "clean" (sharp, faint noise), "normal" (typical camera) or "hard" (poor conditions)."""
    if level == "clean":
        return Photometric(blur_sigma=float(rng.uniform(0.3, 0.7)), noise_sigma=float(rng.uniform(0.0, 1.0)),
                           black_level=float(rng.uniform(5, 20)), white_level=float(rng.uniform(220, 250)))
    if level == "normal":
        return Photometric(
            blur_sigma=float(rng.uniform(0.3, 1.5)),
            gradient=(float(rng.uniform(-0.25, 0.25)), float(rng.uniform(-0.25, 0.25))),
            vignetting=float(rng.uniform(0.0, 0.3)),
            black_level=float(rng.uniform(0, 30)), white_level=float(rng.uniform(190, 255)),
            gamma=float(rng.uniform(0.8, 1.25)), noise_sigma=float(rng.uniform(0.5, 4.0)),
            jpeg_quality=int(rng.integers(75, 96)) if rng.random() < 0.2 else None)
    if level == "hard":
        black = float(rng.uniform(40, 100))
        return Photometric(
            blur_sigma=float(rng.uniform(1.0, 2.5)),
            gradient=(float(rng.uniform(-0.45, 0.45)), float(rng.uniform(-0.45, 0.45))),
            vignetting=float(rng.uniform(0.2, 0.5)),
            black_level=black, white_level=black + float(rng.uniform(50, 110)),
            gamma=float(rng.uniform(0.7, 1.4)), noise_sigma=float(rng.uniform(3.0, 8.0)),
            jpeg_quality=int(rng.integers(60, 90)) if rng.random() < 0.3 else None)
    raise ValueError(f"unknown photometric level {level!r} (clean, normal, hard)")
