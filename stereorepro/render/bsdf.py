"""BSDFs over flat structure-of-arrays batches (float32 numpy).

* **Lambert**: ``f = kd / pi``; cosine-weighted sampling.
* **Glossy** (normalised modified Phong): ``f_s = ks (e + 2) / (2 pi) max(0, r . wi)^e`` with ``r`` the mirror
  direction of ``wo``; sampled around ``r`` with ``pdf = (e + 1) / (2 pi) max(0, r . wi)^e``. A material is
  ``kd`` Lambert + ``ks`` Phong; the lobe is picked with probability proportional to its albedo's luminance.

All directions point away from the surface; ``n`` is the shading normal on the side of ``wo``. Shapes: N paths,
vectors (N, 3), scalars (N,). A diffuse-only scene calls only the ``lambert_*`` functions.

Transcendentals (``cos``, ``sin``, ``pow``) are evaluated in float64 and rounded to float32 (:func:`_cos`,
:func:`_sin`, :func:`_pow`): numpy's float32 SIMD ``cos``/``sin`` differ from libm in the last bit for ~17 % of
arguments, while float64 numpy and float64 libm agree, so the native kernels (``cpp_ext/src/shade_tracer.cpp``, which
call float64 libm and cast) reproduce this module bit for bit. Everything else is float32.
"""

from __future__ import annotations

import numpy as np

__all__ = ["onb", "to_world", "lambert_sample", "lambert_pdf", "phong_eval", "phong_sample",
           "mixture_sample", "mixture_eval"]

_INV_PI = np.float32(1.0 / np.pi)
_TWO_PI = np.float32(2.0 * np.pi)


def _cos(x: np.ndarray) -> np.ndarray:
    return np.cos(x.astype(np.float64)).astype(np.float32)


def _sin(x: np.ndarray) -> np.ndarray:
    return np.sin(x.astype(np.float64)).astype(np.float32)


def _pow(x: np.ndarray, e: np.ndarray) -> np.ndarray:
    return np.power(np.asarray(x).astype(np.float64), np.asarray(e).astype(np.float64)).astype(np.float32)


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of (N, 3) arrays → (N,)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def onb(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (N, 3) completing unit normals ``n`` (N, 3) to an orthonormal basis (Duff et al. 2017)."""
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    s = np.where(z >= 0, np.float32(1), np.float32(-1)).astype(np.float32)
    a = np.float32(-1) / (s + z)
    b = x * y * a
    t = np.stack([1 + s * x * x * a, s * b, -s * x], axis=1)
    bt = np.stack([b, s + y * y * a, -y], axis=1)
    return t, bt


def to_world(n: np.ndarray, lx: np.ndarray, ly: np.ndarray, lz: np.ndarray) -> np.ndarray:
    """Local coordinates (each (N,)) in the frame of ``n`` (N, 3) → world vectors (N, 3)."""
    t, b = onb(n)
    return t * lx[:, None] + b * ly[:, None] + n * lz[:, None]


def lambert_sample(n: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-weighted directions around ``n`` (N, 3) from uniforms (N,). Returns (wi (N, 3), cos (N,))."""
    r = np.sqrt(u1)
    phi = _TWO_PI * u2
    cz = np.sqrt(np.maximum(np.float32(1) - u1, np.float32(0)))
    return to_world(n, r * _cos(phi), r * _sin(phi), cz), cz


def lambert_pdf(cos_i: np.ndarray) -> np.ndarray:
    """Solid-angle pdf of cosine sampling, (N,) → (N,)."""
    return np.maximum(cos_i, np.float32(0)) * _INV_PI


def _reflect(n: np.ndarray, wo: np.ndarray) -> np.ndarray:
    return (2 * dot(n, wo))[:, None] * n - wo


def phong_eval(ks: np.ndarray, exponent: np.ndarray, n: np.ndarray, wo: np.ndarray, wi: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """Glossy lobe value and sampling pdf.

    Args:
        ks: (N, 3) specular albedo; exponent: (N,) Phong exponent; n, wo, wi: (N, 3) unit.

    Returns:
        f_s: (N, 3) BSDF value (without the cosine); pdf_s: (N,) solid-angle pdf of :func:`phong_sample`.
    """
    c = np.maximum(dot(_reflect(n, wo), wi), np.float32(0))
    ce = _pow(c, exponent)
    base = ce * (np.float32(1) / _TWO_PI)
    return ks * (base * (exponent + 2))[:, None], base * (exponent + 1)


def phong_sample(exponent: np.ndarray, n: np.ndarray, wo: np.ndarray, u1: np.ndarray, u2: np.ndarray
                 ) -> np.ndarray:
    """Directions (N, 3) distributed as ``cos^e`` around the mirror direction of ``wo`` (may fall below the surface)."""
    r = _reflect(n, wo)
    ca = _pow(u1, np.float32(1) / (exponent + 1))
    sa = np.sqrt(np.maximum(np.float32(1) - ca * ca, np.float32(0)))
    phi = _TWO_PI * u2
    return to_world(r, sa * _cos(phi), sa * _sin(phi), ca)


def mixture_eval(kd, ks, exponent, p_spec, n, wo, wi):
    """Lambert + glossy: value f (N, 3) and pdf (N,) of :func:`mixture_sample` for directions ``wi`` (N, 3)."""
    cos_i = dot(n, wi)
    f_s, pdf_s = phong_eval(ks, exponent, n, wo, wi)
    f = kd * _INV_PI + f_s
    pdf = (np.float32(1) - p_spec) * lambert_pdf(cos_i) + p_spec * pdf_s
    return f, pdf, cos_i


def mixture_sample(kd, ks, exponent, p_spec, n, wo, u_lobe, u1, u2):
    """Sample Lambert + glossy.

    Args:
        kd, ks: (N, 3); exponent, p_spec (probability of the glossy lobe): (N,); n, wo: (N, 3) unit;
        u_lobe, u1, u2: (N,) uniforms.

    Returns:
        wi: (N, 3); weight = f cos / pdf: (N, 3), zero for invalid samples; pdf: (N,).
    """
    wi_d, _ = lambert_sample(n, u1, u2)
    spec = u_lobe < p_spec
    if spec.any():
        wi_s = phong_sample(exponent[spec], n[spec], wo[spec], u1[spec], u2[spec])
        wi = wi_d.copy()
        wi[spec] = wi_s
    else:
        wi = wi_d
    f, pdf, cos_i = mixture_eval(kd, ks, exponent, p_spec, n, wo, wi)
    ok = (cos_i > 0) & (pdf > 0)
    scale = np.where(ok, cos_i / np.where(ok, pdf, np.float32(1)), np.float32(0)).astype(np.float32)
    return wi, f * scale[:, None], pdf
