"""BSDFs over flat structure-of-arrays batches (float32 numpy).

* **Lambert**: ``f = kd / pi``; cosine-weighted sampling.
* **Glossy** (normalised modified Phong): ``f_s = ks (e + 2) / (2 pi) max(0, r . wi)^e`` with ``r`` the mirror
  direction of ``wo``; sampled around ``r`` with ``pdf = (e + 1) / (2 pi) max(0, r . wi)^e``. A material is
  ``kd`` Lambert + ``ks`` Phong; the lobe is picked with probability proportional to its albedo's luminance.

All directions point away from the surface; ``n`` is the shading normal on the side of ``wo``. Shapes: N paths,
vectors (N, 3), scalars (N,). A diffuse-only scene calls only the ``lambert_*`` functions.

Bit parity with the native kernels (``cpp_ext/src/shade_tracer.cpp``): every float32 operation is written in the
same order there. The azimuth of a sampled direction, ``(cos 2πu, sin 2πu)``, comes from :func:`unit_circle`, a
float32 polynomial that both sides evaluate operation by operation (libm's float64 ``sincos`` took about a sixth of
the native first-bounce shading). ``pow`` (glossy lobes only) is evaluated in float64 and rounded to float32
(:func:`_pow`): numpy's float32 SIMD transcendentals differ from libm in the last bit, float64 numpy and float64
libm agree. Everything else is float32.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "onb",
    "to_world",
    "unit_circle",
    "lambert_sample",
    "lambert_pdf",
    "phong_eval",
    "phong_sample",
    "mixture_sample",
    "mixture_eval",
]

_INV_PI = np.float32(1.0 / np.pi)
_TWO_PI = np.float32(2.0 * np.pi)


_HALF_PI = np.float32(np.pi / 2)
# Taylor coefficients of sin and cos, enough for |error| < 6e-8 on [0, pi/2] (float32 resolution).
_SIN = tuple(np.float32(c) for c in (-1 / 6, 1 / 120, -1 / 5040, 1 / 362880, -1 / 39916800))
_COS = tuple(np.float32(c) for c in (-1 / 2, 1 / 24, -1 / 720, 1 / 40320, -1 / 3628800, 1 / 479001600))


def unit_circle(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(cos 2πu, sin 2πu)`` for uniforms ``u`` in [0, 1) (N,) float32, to within 3e-7.

    The quadrant ``q = floor(4u)`` is split off exactly, the angle ``a = (4u − q)·π/2`` in [0, π/2) goes through
    Horner polynomials, and the quadrant rotates the result. The native kernels evaluate the same operations in
    the same order (``unit_circle`` in ``cpp_ext/src/shade_tracer.cpp``), so both give the same bits.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.bsdf import unit_circle
        >>> c, s = unit_circle(np.array([0.0, 0.25, 0.5, 0.125], np.float32))
        >>> [round(float(x), 4) + 0.0 for x in c], [round(float(x), 4) + 0.0 for x in s]
        ([1.0, 0.0, -1.0, 0.7071], [0.0, 1.0, 0.0, 0.7071])
    """
    u = np.asarray(u, np.float32)
    u4 = u * np.float32(4)
    q = np.floor(u4)
    a = (u4 - q) * _HALF_PI
    a2 = a * a
    s1, s2, s3, s4, s5 = _SIN
    c1, c2, c3, c4, c5, c6 = _COS
    one = np.float32(1)
    s = a * (one + a2 * (s1 + a2 * (s2 + a2 * (s3 + a2 * (s4 + a2 * s5)))))
    c = one + a2 * (c1 + a2 * (c2 + a2 * (c3 + a2 * (c4 + a2 * (c5 + a2 * c6)))))
    cos = np.where(q == 0, c, np.where(q == 1, -s, np.where(q == 2, -c, s)))
    sin = np.where(q == 0, s, np.where(q == 1, c, np.where(q == 2, -s, -c)))
    return cos, sin


def _pow(x: np.ndarray, e: np.ndarray) -> np.ndarray:
    return np.power(np.asarray(x).astype(np.float64), np.asarray(e).astype(np.float64)).astype(np.float32)


def dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of (N, 3) arrays → (N,)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def onb(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (N, 3) completing unit normals ``n`` (N, 3) to an orthonormal basis (Duff et al. 2017).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.bsdf import onb
        >>> n = np.array([[0, 0, 1], [0, -1, 0]], np.float32)
        >>> t, b = onb(n)
        >>> basis = np.stack([t, b, n], axis=1)  # (N, 3, 3), rows t, b, n
        >>> bool(np.allclose(basis @ basis.transpose(0, 2, 1), np.eye(3), atol=1e-6))
        True
    """
    x, y, z = n[:, 0], n[:, 1], n[:, 2]
    s = np.where(z >= 0, np.float32(1), np.float32(-1)).astype(np.float32)
    a = np.float32(-1) / (s + z)
    b = x * y * a
    t = np.stack([1 + s * x * x * a, s * b, -s * x], axis=1)
    bt = np.stack([b, s + y * y * a, -y], axis=1)
    return t, bt


def to_world(n: np.ndarray, lx: np.ndarray, ly: np.ndarray, lz: np.ndarray) -> np.ndarray:
    """Local coordinates (each (N,)) in the frame of ``n`` (N, 3) → world vectors (N, 3).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.bsdf import to_world
        >>> n = np.array([[0, 1, 0]], np.float32)
        >>> one, zero = np.ones(1, np.float32), np.zeros(1, np.float32)
        >>> to_world(n, zero, zero, one).tolist()
        [[0.0, 1.0, 0.0]]
    """
    t, b = onb(n)
    return t * lx[:, None] + b * ly[:, None] + n * lz[:, None]


def lambert_sample(n: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-weighted directions around ``n`` (N, 3) from uniforms (N,). Returns (wi (N, 3), cos (N,)).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.bsdf import lambert_sample
        >>> rng = np.random.default_rng(0)
        >>> n = np.tile(np.array([[0, 0, 1]], np.float32), (100, 1))
        >>> u1, u2 = rng.random(100, dtype=np.float32), rng.random(100, dtype=np.float32)
        >>> wi, cos = lambert_sample(n, u1, u2)
        >>> unit = np.allclose(np.linalg.norm(wi, axis=1), 1, atol=1e-5)
        >>> wi.shape, bool((cos >= 0).all()), bool(np.allclose(wi[:, 2], cos)), bool(unit)
        ((100, 3), True, True, True)
    """
    r = np.sqrt(u1)
    cph, sph = unit_circle(u2)
    cz = np.sqrt(np.maximum(np.float32(1) - u1, np.float32(0)))
    return to_world(n, r * cph, r * sph, cz), cz


def lambert_pdf(cos_i: np.ndarray) -> np.ndarray:
    """Solid-angle pdf of cosine sampling, (N,) → (N,).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.bsdf import lambert_pdf
        >>> [round(float(p), 4) for p in lambert_pdf(np.array([1.0, 0.5, -0.3], np.float32))]
        [0.3183, 0.1592, 0.0]
    """
    return np.maximum(cos_i, np.float32(0)) * _INV_PI


def _reflect(n: np.ndarray, wo: np.ndarray) -> np.ndarray:
    return (2 * dot(n, wo))[:, None] * n - wo


def phong_eval(
    ks: np.ndarray, exponent: np.ndarray, n: np.ndarray, wo: np.ndarray, wi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Glossy lobe value and sampling pdf.

    Args:
        ks: (N, 3) specular albedo; exponent: (N,) Phong exponent; n, wo, wi: (N, 3) unit.

    Returns:
        f_s: (N, 3) BSDF value (without the cosine); pdf_s: (N,) solid-angle pdf of :func:`phong_sample`.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.bsdf import phong_eval
        >>> n = np.array([[0, 0, 1]], np.float32)
        >>> wo = np.array([[0.6, 0, 0.8]], np.float32); mirror = np.array([[-0.6, 0, 0.8]], np.float32)
        >>> f, pdf = phong_eval(np.full((1, 3), 0.5, np.float32), np.array([10.0], np.float32), n, wo, mirror)
        >>> f.shape, round(float(f[0, 0]), 4), round(float(pdf[0]), 4)
        ((1, 3), 0.9549, 1.7507)
    """
    c = np.maximum(dot(_reflect(n, wo), wi), np.float32(0))
    ce = _pow(c, exponent)
    base = ce * (np.float32(1) / _TWO_PI)
    return ks * (base * (exponent + 2))[:, None], base * (exponent + 1)


def phong_sample(exponent: np.ndarray, n: np.ndarray, wo: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Directions (N, 3) distributed as ``cos^e`` around the mirror direction of ``wo`` (may fall below the surface).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.bsdf import phong_sample
        >>> n = np.array([[0, 0, 1]] * 2, np.float32); wo = np.array([[0.6, 0, 0.8]] * 2, np.float32)
        >>> u1, u2 = np.full(2, 0.5, np.float32), np.array([0.1, 0.7], np.float32)
        >>> wi = phong_sample(np.full(2, 1e6, np.float32), n, wo, u1, u2)  # a near-mirror lobe
        >>> [[round(float(x), 2) + 0.0 for x in w] for w in wi]
        [[-0.6, 0.0, 0.8], [-0.6, 0.0, 0.8]]
    """
    r = _reflect(n, wo)
    ca = _pow(u1, np.float32(1) / (exponent + 1))
    sa = np.sqrt(np.maximum(np.float32(1) - ca * ca, np.float32(0)))
    cph, sph = unit_circle(u2)
    return to_world(r, sa * cph, sa * sph, ca)


def mixture_eval(kd, ks, exponent, p_spec, n, wo, wi):
    """Lambert + glossy: value f (N, 3) and pdf (N,) of :func:`mixture_sample` for directions ``wi`` (N, 3).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.bsdf import mixture_eval
        >>> n = np.array([[0, 0, 1]], np.float32); wo = wi = n
        >>> kd, ks = np.full((1, 3), 0.5, np.float32), np.zeros((1, 3), np.float32)
        >>> exponent, p_spec = np.array([10.0], np.float32), np.array([0.0], np.float32)
        >>> f, pdf, cos_i = mixture_eval(kd, ks, exponent, p_spec, n, wo, wi)
        >>> round(float(f[0, 0]), 4), round(float(pdf[0]), 4), float(cos_i[0])
        (0.1592, 0.3183, 1.0)
    """
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

    Examples:
        >>> import numpy as np
        >>> from stereorepro.render.bsdf import mixture_sample
        >>> rng = np.random.default_rng(0)
        >>> N = 8
        >>> n = np.tile(np.array([[0, 0, 1]], np.float32), (N, 1))
        >>> wo = np.tile(np.array([[0.6, 0, 0.8]], np.float32), (N, 1))
        >>> kd, ks = np.full((N, 3), 0.5, np.float32), np.zeros((N, 3), np.float32)
        >>> u = [rng.random(N, dtype=np.float32) for _ in range(3)]
        >>> exponent, p_spec = np.full(N, 10, np.float32), np.zeros(N, np.float32)  # diffuse only
        >>> wi, weight, pdf = mixture_sample(kd, ks, exponent, p_spec, n, wo, *u)
        >>> wi.shape, bool(np.allclose(weight, 0.5)), bool((pdf > 0).all())
        ((8, 3), True, True)
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
