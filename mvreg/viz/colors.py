"""Colors for recordings and colored outputs, in plain numpy (no matplotlib)."""

from __future__ import annotations

import numpy as np

# Viridis at 11 evenly spaced stops; linear interpolation between them is visually
# indistinguishable from the full 256-entry table.
_VIRIDIS_STOPS = np.array(
    [
        [0.267004, 0.004874, 0.329415],
        [0.282623, 0.140926, 0.457517],
        [0.253935, 0.265254, 0.529983],
        [0.206756, 0.371758, 0.553117],
        [0.163625, 0.471133, 0.558148],
        [0.127568, 0.566949, 0.550556],
        [0.134692, 0.658636, 0.517649],
        [0.266941, 0.748751, 0.440573],
        [0.477504, 0.821444, 0.318195],
        [0.741388, 0.873449, 0.149561],
        [0.993248, 0.906157, 0.143936],
    ]
)


def scan_colors(num_scans: int) -> np.ndarray:
    """Distinct, saturated colors, one per scan, stable for a given index.

    Hues follow the golden-ratio sequence so neighbouring indices are far apart on the
    color wheel. Returns ``(num_scans, 3) uint8``.
    """
    index = np.arange(num_scans, dtype=np.float64)
    hue = (0.05 + index * 0.618033988749895) % 1.0
    saturation = np.where(index % 2 == 0, 0.85, 0.65)
    value = np.where(index % 3 == 2, 0.80, 0.95)
    return (_hsv_to_rgb(hue, saturation, value) * 255.0 + 0.5).astype(np.uint8)


def viridis(values: np.ndarray, vmin: float = 0.0, vmax: float = 1.0) -> np.ndarray:
    """Map ``(N,)`` values to viridis colors, clipped to ``[vmin, vmax]``.

    Non-finite values map to the top of the scale. Returns ``(N, 3) uint8``.
    """
    values = np.asarray(values, dtype=np.float64)
    span = vmax - vmin if vmax > vmin else 1.0
    t = np.clip((values - vmin) / span, 0.0, 1.0)
    t = np.where(np.isfinite(t), t, 1.0)
    stops = np.linspace(0.0, 1.0, len(_VIRIDIS_STOPS))
    rgb = np.stack([np.interp(t, stops, _VIRIDIS_STOPS[:, c]) for c in range(3)], axis=-1)
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def residual_colors(
    residuals: np.ndarray, clip_percentile: float = 95.0
) -> tuple[np.ndarray, float]:
    """Color ``(N,)`` non-negative residuals with viridis, clipped at a robust percentile.

    Returns ``((N, 3) uint8 colors, clip value)``: residuals at or above the clip value
    are drawn yellow, zero is dark purple.
    """
    residuals = np.asarray(residuals, dtype=np.float64)
    finite = residuals[np.isfinite(residuals)]
    clip = float(np.percentile(finite, clip_percentile)) if finite.size else 1.0
    if not clip > 0.0:
        clip = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
    return viridis(residuals, 0.0, clip), clip


def _hsv_to_rgb(hue: np.ndarray, saturation: np.ndarray, value: np.ndarray) -> np.ndarray:
    """Vectorised HSV -> RGB, all in [0, 1]; returns ``(N, 3) float64``."""
    sector = np.floor(hue * 6.0).astype(int) % 6
    f = hue * 6.0 - np.floor(hue * 6.0)
    p = value * (1.0 - saturation)
    q = value * (1.0 - f * saturation)
    t = value * (1.0 - (1.0 - f) * saturation)
    table = np.stack(
        [
            np.stack([value, t, p], -1),
            np.stack([q, value, p], -1),
            np.stack([p, value, t], -1),
            np.stack([p, q, value], -1),
            np.stack([t, p, value], -1),
            np.stack([value, p, q], -1),
        ]
    )
    return table[sector, np.arange(len(hue))]
