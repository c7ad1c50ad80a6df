"""What a real camera does to the rendered scene: exposure, auto-exposure, vignetting, gains, noise.

The renderer gives the scene's *radiance* as grey levels (the texture as photographed, 0-255,
float). A frame of camera ``c`` at frame ``k`` is then

    I = clip(round(radiance_avg * B_k * V(r) * g_c + noise), 0, 255)

- ``radiance_avg``: the radiance averaged over the exposure window ``[t - E_k, t]`` that ends
  at the frame's true time ``t`` (motion blur; the generator renders sub-frames over the window,
  and with a rolling shutter each row band at its own time);
- ``B_k = L(t) * G_k * E_k / exposure_ref_s``: the brightness, from the scene illumination
  ``L(t) = exp(illumination_log_amplitude * s(t))`` (``s`` a sum of two slow sinusoids of
  random phase, in [-1, 1]) and the auto-exposure's exposure time ``E_k`` and analogue gain
  ``G_k`` (:func:`exposure_schedule`); with auto-exposure off, ``E_k = exposure_s`` (the
  blur window only) and ``B = L(t)`` (1 unless the illumination varies);
- ``V(r) = cos^4(atan(rho * tan(theta_c)))``: natural vignetting, ``rho`` the distance to the
  principal point over the distance of the farthest image corner, ``theta_c`` chosen so that the
  corners get ``1 - vignetting``;
- ``g_c``: 1 for the left camera, ``stereo_gain`` for the right (a gain mismatch);
- noise: Gaussian with the variance of a Poisson-Gaussian sensor, ``sigma^2 = (read_noise_std
  * G_k)^2 + shot_noise_gl * G_k * S`` (``S`` the signal in grey levels; ``shot_noise_gl`` is
  grey levels per photo-electron at unit gain): it grows with the signal and the gain.

Everything is deterministic by the sequence's seed: the illumination's phases, and the noise
per (seed, frame, camera).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from slam.core.calibration import CameraIntrinsics
from slam.core.errors import InputError

if TYPE_CHECKING:
    from datasets.synth.imu_sim import ImuEffects


@dataclass(frozen=True)
class CameraEffects:
    """The camera effects of a synthetic sequence (all off by default: the clean images)."""

    exposure_s: float = 0.0  # fixed exposure time (motion blur) when auto-exposure is off
    auto_exposure: bool = False  # exposure time and gain follow the scene illumination
    exposure_ref_s: float = 0.005  # exposure at gain 1 that gives the clean brightness at L = 1
    exposure_min_s: float = 0.0002  # auto-exposure bounds
    exposure_max_s: float = 0.010
    gain_step: float = 2.0**0.5  # analogue gain ladder (3 dB steps) from 1 to gain_max
    gain_max: float = 8.0
    ae_rate: float = 0.35  # share of the log brightness error the AE corrects per frame
    illumination_log_amplitude: float = 0.0  # L(t) in exp(+-a): 0.9 gives x0.41 .. x2.46
    illumination_period_s: float = 24.0  # period of the slower sinusoid (the other: / 2.7)
    vignetting: float = 0.0  # darkening at the image corners (0.3: corners at 70 %)
    stereo_gain: float = 1.0  # right camera's gain over the left's
    read_noise_std: float = 0.0  # grey levels at gain 1
    shot_noise_gl: float = 0.0  # grey levels per photo-electron at gain 1 (shot noise)
    line_delay_s: float = 0.0  # rolling shutter: row r ends exposure (r - (H-1)/2) * delay later
    subframe_spacing_px: float = 1.5  # motion blur: image motion between rendered sub-frames
    max_subframes: int = 24

    @property
    def active(self) -> bool:
        """Whether any effect changes the clean render."""
        return self != CameraEffects()

    @property
    def blurs(self) -> bool:
        return self.auto_exposure or self.exposure_s > 0

    def replace(self, **changes: object) -> CameraEffects:
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]

    def validate(self) -> None:
        """InputError (one line, naming the parameter) for values outside their bounds."""
        bounds = {
            "exposure_s": (0.0, 0.05),
            "exposure_ref_s": (1e-5, 0.05),
            "exposure_min_s": (1e-6, 0.05),
            "exposure_max_s": (1e-5, 0.05),
            "gain_step": (1.01, 4.0),
            "gain_max": (1.0, 64.0),
            "ae_rate": (0.01, 1.0),
            "illumination_log_amplitude": (0.0, 3.0),
            "illumination_period_s": (0.5, 3600.0),
            "vignetting": (0.0, 0.9),
            "stereo_gain": (0.5, 2.0),
            "read_noise_std": (0.0, 50.0),
            "shot_noise_gl": (0.0, 10.0),
            "line_delay_s": (0.0, 200e-6),
            "subframe_spacing_px": (0.25, 20.0),
            "max_subframes": (1, 256),
        }
        for name, (lo, hi) in bounds.items():
            v = getattr(self, name)
            if not lo <= v <= hi:
                raise InputError(f"camera effect {name} = {v} is outside [{lo}, {hi}]")
        if self.exposure_min_s > self.exposure_max_s:
            raise InputError("camera effect exposure_min_s is above exposure_max_s")


def realistic_camera() -> CameraEffects:
    """The ``--camera realistic`` bundle: EuRoC-like VI-sensor behaviour (MT9V034 global
    shutter, so no rolling shutter): auto-exposure between 0.2 and 10 ms with 3 dB gain steps
    over a scene whose illumination drifts by x0.3-x3.3, 30 % corner vignetting, a 3 % stereo
    gain mismatch, read noise 1.2 grey levels and shot noise of 40 electrons per grey level."""
    return CameraEffects(
        auto_exposure=True,
        illumination_log_amplitude=1.2,
        vignetting=0.3,
        stereo_gain=1.03,
        read_noise_std=1.2,
        shot_noise_gl=1.0 / 40.0,
    )


CAMERA_BUNDLES = ("clean", "realistic")


def rig_effects(bundle: str) -> tuple[CameraEffects, ImuEffects]:
    """The camera and IMU effects of a ``slam synth --camera`` bundle: ``clean`` (none) or
    ``realistic`` (:func:`realistic_camera` and :func:`datasets.synth.imu_sim.realistic_imu`)."""
    from datasets.synth.imu_sim import ImuEffects, realistic_imu

    if bundle == "clean":
        return CameraEffects(), ImuEffects()
    if bundle == "realistic":
        return realistic_camera(), realistic_imu()
    raise InputError(f"camera bundle must be one of {', '.join(CAMERA_BUNDLES)}, got {bundle!r}")


@dataclass(frozen=True, eq=False)
class ExposureSchedule:
    """Per frame (N,): scene illumination, exposure time (s), analogue gain, brightness."""

    illumination: np.ndarray
    exposure_s: np.ndarray
    gain: np.ndarray
    exposure_ref_s: float

    @property
    def brightness(self) -> np.ndarray:
        """B_k, the factor on the rendered radiance (before vignetting and stereo gain)."""
        return self.illumination * self.gain * self.exposure_s / self.exposure_ref_s


def illumination(effects: CameraEffects, t_s: np.ndarray, seed: int) -> np.ndarray:
    """Scene illumination L(t) (1 = the clean render's), smooth, deterministic by seed."""
    a = effects.illumination_log_amplitude
    t = np.asarray(t_s, dtype=np.float64)
    if a == 0:
        return np.ones_like(t)
    phases = np.random.default_rng([seed, 77]).uniform(0, 2 * np.pi, 2)
    w = 2 * np.pi / effects.illumination_period_s
    s = 0.65 * np.sin(w * t + phases[0]) + 0.35 * np.sin(2.7 * w * t + phases[1])
    return np.exp(a * s)


def exposure_schedule(effects: CameraEffects, t_s: np.ndarray, seed: int = 0) -> ExposureSchedule:
    """Exposure and gain of every frame at true times ``t_s`` (in order).

    Auto-exposure: the controller wants ``E * G / exposure_ref_s = 1 / L`` and moves its log
    towards that by ``ae_rate`` per frame (a lag). The gain is raised one step when the wanted
    exposure exceeds ``exposure_max_s`` and lowered when it would still fit under
    ``exposure_max_s / gain_step**1.5`` (hysteresis); the new gain takes effect one frame
    before the matching exposure (as sensors latch gain and exposure registers on different
    frames), so each gain step is an abrupt brightness step of ``gain_step`` for one frame.
    """
    t = np.asarray(t_s, dtype=np.float64)
    n = len(t)
    light = illumination(effects, t, seed)
    if not effects.auto_exposure:
        e_s = effects.exposure_s if effects.exposure_s > 0 else effects.exposure_ref_s
        return ExposureSchedule(light, np.full(n, e_s), np.ones(n), e_s)
    ref = effects.exposure_ref_s
    exposure = np.empty(n)
    gain = np.empty(n)
    log_p = -np.log(light[0]) if n else 0.0  # starts converged
    top = int(np.floor(np.log(effects.gain_max) / np.log(effects.gain_step) + 1e-9))
    level, e_prev = 0, ref  # gain = gain_step ** level
    for k in range(n):
        log_p += effects.ae_rate * (-np.log(light[k]) - log_p)
        wanted_total_s = ref * float(np.exp(log_p))  # E * G
        old_level = level
        g = effects.gain_step**level
        if wanted_total_s / g > effects.exposure_max_s and level < top:
            level += 1
        elif level > 0 and wanted_total_s / (g / effects.gain_step) < (
            effects.exposure_max_s / effects.gain_step**1.5
        ):
            level -= 1
        g = effects.gain_step**level
        e = float(np.clip(wanted_total_s / g, effects.exposure_min_s, effects.exposure_max_s))
        if level != old_level:
            e = e_prev  # the exposure catches up one frame later
        exposure[k], gain[k], e_prev = e, g, e
    return ExposureSchedule(light, exposure, gain, ref)


def vignetting_map(effects: CameraEffects, intrinsics: CameraIntrinsics) -> np.ndarray:
    """(H, W) float32 ``V``: cos^4 falloff about the principal point, ``1 - vignetting`` at
    the farthest corner."""
    h, w = intrinsics.height, intrinsics.width
    if effects.vignetting <= 0:
        return np.ones((h, w), np.float32)
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    r = np.hypot(uu - intrinsics.cx, vv - intrinsics.cy)
    corners = [(0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1)]
    r_max = max(np.hypot(x - intrinsics.cx, y - intrinsics.cy) for x, y in corners)
    return vignetting_profile(effects.vignetting, r / r_max).astype(np.float32)


def vignetting_profile(vignetting: float, rho: np.ndarray) -> np.ndarray:
    """``cos^4(atan(rho * tan(theta_c)))`` with ``cos^4(theta_c) = 1 - vignetting``."""
    tan_c = np.tan(np.arccos((1.0 - vignetting) ** 0.25))
    return 1.0 / (1.0 + (np.asarray(rho) * tan_c) ** 2) ** 2


def sensor_image(
    radiance: np.ndarray,
    scale: np.ndarray | float,
    gain: float,
    effects: CameraEffects,
    rng: np.random.Generator | None,
) -> np.ndarray:
    """uint8 image from the float radiance: ``radiance * scale`` (brightness x vignetting x
    stereo gain) plus signal-dependent noise, rounded and clipped (saturation)."""
    signal = radiance * np.asarray(scale, dtype=np.float32)
    noisy_var = effects.read_noise_std > 0 or effects.shot_noise_gl > 0
    if noisy_var and rng is not None:
        var = np.maximum(signal, np.float32(0.0)) * np.float32(effects.shot_noise_gl * gain)
        var += np.float32((effects.read_noise_std * gain) ** 2)
        noise = rng.standard_normal(signal.shape, dtype=np.float32)
        noise *= np.sqrt(var)
        signal = signal + noise
    return np.clip(np.round(signal), 0, 255).astype(np.uint8)
