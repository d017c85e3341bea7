"""Log-Gabor filter bank and the Maximum Index Map (paper Eqs. 5-10, numbers from ALGORITHM.md).

The bank lives in the frequency domain and is built once per image shape (LRU cache). One forward FFT, then
per (scale, orientation) a complex inverse FFT (OpenCV's, float32: about twice as fast here as numpy/scipy's);
amplitudes are summed over scales and the MIM is 1 + the index of the strongest orientation (0 where the
strongest amplitude is negligible). The 1/(H W) of the inverse transform is folded into the cached bank.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
import scipy.fft as sfft

from .config import MimConfig
from .parallel import run_parts


def frequency_grid(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Radius r and angle theta of each FFT bin, in the unshifted (FFT) order; r[0, 0] = 1 (DC guard)."""
    rows, cols = shape
    v = sfft.fftfreq(rows)  # cycles/px along rows, in [-0.5, 0.5)
    u = sfft.fftfreq(cols)
    uu, vv = np.meshgrid(u, v)
    r = np.sqrt(uu**2 + vv**2)
    theta = np.arctan2(-vv, uu)
    r[0, 0] = 1.0
    return r, theta


def radial_filters(r: np.ndarray, cfg: MimConfig) -> np.ndarray:
    """(Ns, H, W) radial log-Gabor components times the Butterworth low-pass, zero at DC."""
    lowpass = 1.0 / (1.0 + (r / cfg.lowpass_cutoff) ** (2 * cfg.lowpass_order))
    out = np.empty((cfg.n_scales,) + r.shape)
    denom = 2.0 * np.log(cfg.sigma_on_f) ** 2
    for s in range(cfg.n_scales):
        f0 = 1.0 / (cfg.min_wavelength_px * cfg.mult**s)
        g = np.exp(-(np.log(r / f0) ** 2) / denom) * lowpass
        g[0, 0] = 0.0
        out[s] = g
    return out


def angular_filters(theta: np.ndarray, cfg: MimConfig) -> np.ndarray:
    """(No, H, W) raised-cosine angular windows centred at phi_o = o*pi/No, zero beyond pi/No."""
    out = np.empty((cfg.n_orient,) + theta.shape)
    for o in range(cfg.n_orient):
        phi = o * np.pi / cfg.n_orient
        dtheta = np.abs(np.arctan2(np.sin(theta - phi), np.cos(theta - phi)))
        dtheta = np.minimum(dtheta * cfg.n_orient, np.pi)
        out[o] = (np.cos(dtheta) + 1.0) / 2.0
    return out


@lru_cache(maxsize=8)
def filter_bank(shape: tuple[int, int], cfg: MimConfig) -> np.ndarray:
    """(No, Ns, H, W) complex64-ready float32 bank G_s * S_o for an FFT of ``shape``; cached per shape."""
    r, theta = frequency_grid(shape)
    radial = radial_filters(r, cfg)
    angular = angular_filters(theta, cfg)
    bank = (angular[:, None] * radial[None, :]).astype(np.float32)
    bank.setflags(write=False)
    return bank


@lru_cache(maxsize=2)
def _bank_two_channel(shape: tuple[int, int], cfg: MimConfig) -> np.ndarray:
    """(No, Ns, H, W, 2) float32: the bank duplicated over (re, im), scaled by 1/(H W) for the inverse DFT."""
    bank = filter_bank(shape, cfg) / np.float32(shape[0] * shape[1])
    out = np.repeat(bank[..., None], 2, axis=-1).astype(np.float32)
    out.setflags(write=False)
    return out


def fft_shape(image_shape: tuple[int, int], margin: int) -> tuple[int, int]:
    return tuple(cv2.getOptimalDFTSize(n + 2 * margin) for n in image_shape)  # type: ignore[return-value]


def _spectrum(image: np.ndarray, cfg: MimConfig) -> tuple[np.ndarray, tuple[int, int]]:
    h, w = image.shape
    m = cfg.fft_margin_px
    shape = fft_shape((h, w), m)
    padded = np.zeros(shape, dtype=np.float32)
    padded[m : m + h, m : m + w] = image
    return cv2.dft(padded, flags=cv2.DFT_COMPLEX_OUTPUT), shape  # (H, W, 2)


def orientation_amplitudes(image: np.ndarray, cfg: MimConfig, orientations=None, spectrum=None):
    """Yield (o, A_o) for each orientation: A_o = sum_s |IFFT(F * G_s * S_o)| (H, W) float32, margin cropped.
    The yielded array is reused: consume it before advancing."""
    h, w = image.shape
    m = cfg.fft_margin_px
    if spectrum is None:
        spectrum, shape = _spectrum(image, cfg)
    else:
        shape = spectrum.shape[:2]
    bank = _bank_two_channel(shape, cfg)
    # Every buffer is allocated once per call and written in place: fresh 1.5 MB temporaries per transform cost
    # more in page faults than the transform itself (measured: magnitude 0.45 ms -> 0.13 ms per filter).
    product = np.empty(shape + (2,), dtype=np.float32)
    response = np.empty_like(product)
    re, im, mag, acc = (np.empty((h, w), dtype=np.float32) for _ in range(4))
    for o in range(cfg.n_orient) if orientations is None else orientations:
        acc.fill(0.0)
        for s in range(cfg.n_scales):
            cv2.multiply(spectrum, bank[o, s], dst=product)
            cv2.idft(product, dst=response, flags=cv2.DFT_COMPLEX_OUTPUT)
            cv2.split(response[m : m + h, m : m + w], [re, im])  # only the image, not the zero margin
            cv2.magnitude(re, im, mag)
            cv2.add(acc, mag, dst=acc)
        yield o, acc


def _running_max(pairs, shape) -> tuple[np.ndarray, np.ndarray]:
    """Arg-max (1-based index) and max over a sequence of (index, map); the earliest index wins ties."""
    max_amp = np.full(shape, -1.0, dtype=np.float32)
    idx = np.zeros(shape, dtype=np.uint8)
    for o, amp in pairs:
        better = cv2.compare(amp, max_amp, cv2.CMP_GT)
        idx[better > 0] = o + 1
        cv2.max(max_amp, amp, dst=max_amp)
    return idx, max_amp


def maximum_index_map(image: np.ndarray, cfg: MimConfig | None = None):
    """BV image (uint8 or float, 0..255) -> (MIM uint8 in 0..No, max amplitude float32), both image-sized.
    The arg-max over orientations is kept incrementally (the first orientation wins ties); with cfg.threads > 1
    contiguous groups of orientations run in parallel and are merged in order (the same result)."""
    cfg = cfg or MimConfig()
    image = np.asarray(image, dtype=np.float32)
    spectrum, _ = _spectrum(image, cfg)
    groups = [g for g in np.array_split(np.arange(cfg.n_orient), cfg.threads) if len(g)]

    def run(group):
        return _running_max(orientation_amplitudes(image, cfg, group, spectrum), image.shape)

    parts = run_parts(run, groups)
    mim, max_amp = parts[0]
    for part_mim, part_max in parts[1:]:
        better = cv2.compare(part_max, max_amp, cv2.CMP_GT)
        mim[better > 0] = part_mim[better > 0]
        cv2.max(max_amp, part_max, dst=max_amp)
    mim[max_amp <= cfg.min_amplitude] = 0
    return mim, max_amp
