// Fused backward reprojection (stereo and temporal), the native twin of stereorepro.reproject.backward_reproject
// (hard tests, float32) and of temporal_reproject (warp + temporal_blend in the same pass); and the twin of
// fast_history_clamp (at the end of the file).
//
// One pass per destination pixel: unproject with the destination depth, project into the source camera, read the
// 2x2 bilinear taps (or the nearest one), run the accept tests (in frame, source surface, position, normal,
// finite values), renormalise the accepted weights and write values / valid / reason / confidence (stereo) or the
// blended colour / history length / valid (temporal). Conventions: stereorepro/camera.py.
//
// Bit-parity with the torch reference matters for the accept decisions (d² <= thr² ties), so the float32
// arithmetic below follows the torch code operation by operation, in the same order, without FMA contraction:
//   wx = ((P00*u + P01*v) + P02) + kt0 * (1/z),  u_s = wx / wz,  x = u_s - 0.5,  x0 = floor(x),  fx = x - x0
//   q  = ((M[i,0]*u + M[i,1]*v) + M[i,2]) * z + t[i]
//   px = z_s * ((Ki00*ut + Ki01*vt) + Ki02),  py = z_s * (Ki11*vt + Ki12)
//   d² = ((qx-px)² + (qy-py)²) + (qz-z_s)²,   |dn|² = (dn0² + dn1²) + dn2²
// The camera matrices (P, kt, M, t, Ks_inv: the fields pixel_src_from_pixel_dst, K_src_t, ray_src_from_pixel_dst,
// t_src_from_dst, K_src_inv of stereorepro.camera.Warp) are composed in Python by stereorepro.camera.compose_warp
// (float64, then cast), the same helper the torch path uses. Layout: NCHW, C-contiguous, CPU.
//
// Motion vectors (optional, of the destination view, float32 or float16 planes): the source position is
// `pixel + motion` instead of the projection, and the position test compares the source tap with
// q + R_src * motion_world (R_src the source camera's rotation); non-finite motion reads no tap (OUT_OF_FRAME), and
// BEHIND_CAMERA means the moved point's z <= 0 (the torch reference's _motion_source, same arithmetic order).
//
// Plane test (plane = true, Thresholds(position_test="plane")): per destination pixel the normal in the source
// camera's axes nc_i = (R[i,0]*n0 + R[i,1]*n1) + R[i,2]*n2 (n the raw normal, 0 where |n|² < 0.25 or not finite:
// "unusable"), the view ray r_i = (M[i,0]*u + M[i,1]*v) + M[i,2] and
//   scale = z / (0.05 + 0.95 * (|(nc0*r0 + nc1*r1) + nc2*r2| / sqrt((r0² + r1²) + r2²))),
//   thr2 = pos_thr2 * (scale*scale)   (-1 where unusable: no tap passes);
// a tap passes the position test iff dist² <= thr2, dist = (nc0*dx + nc1*dy) + nc2*dz (the torch reference's
// _general.plane_terms and _tap_terms, same order).
//
// Image dtypes: every image plane (colour / values, depths, normals, history length, current colour) is float32
// or float16, each on its own (mixed inputs need no conversion); float16 planes are widened exactly on load
// (F16C vcvtph2ps in the vector path, half_to_float in the scalar one) and all arithmetic stays the float32 above,
// so a float16 input gives what torch computes on its float32 upcast. The colour output is float32 or float16
// (torch's `.to(dtype)`: round to nearest, ties to even); valid, reason, confidence and history length keep their
// types (bool, uint8, float32, float32).
#if defined(__clang__)
#pragma clang fp contract(off)
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/optional.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <optional>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define SR_AVX2_PATH 1
// deliberately not "fma": nothing may be fused. F16C: the float16 loads and stores (every AVX2 CPU has it).
#define SR_AVX2 __attribute__((target("avx2,f16c")))
#endif
// The per-tap helpers must be inlined into the row loops (the instantiations per dtype layout would otherwise
// exceed the compiler's inlining budget, and the calls cost time).
#if defined(__GNUC__) || defined(__clang__)
#define SR_INLINE inline __attribute__((always_inline))
#define SR_LAMBDA_INLINE __attribute__((always_inline))
#else
#define SR_INLINE inline
#define SR_LAMBDA_INLINE
#endif

namespace nb = nanobind;

namespace {

using CF = nb::ndarray<const float, nb::c_contig, nb::device::cpu>;
using OF = nb::ndarray<float, nb::c_contig, nb::device::cpu>;
using CA = nb::ndarray<nb::ro, nb::c_contig, nb::device::cpu>;  // image input: float32 or float16 (checked)
using OA = nb::ndarray<nb::c_contig, nb::device::cpu>;          // image output: float32 or float16 (checked)
using OB = nb::ndarray<bool, nb::c_contig, nb::device::cpu>;
using OU8 = nb::ndarray<uint8_t, nb::c_contig, nb::device::cpu>;

// Values of stereorepro.reproject.Reason.
enum : uint8_t { KEPT = 0, NO_SURFACE_DST = 1, BEHIND_CAMERA = 2, OUT_OF_FRAME = 3, NO_SURFACE_SRC = 4,
                 POSITION = 5, NORMAL = 6, NONFINITE = 7 };

constexpr int kMaxStackChannels = 16;

// Mirrors of stereorepro/reproject/_constants.py (exported as _core.reproject_constants, and compared with the
// Python values by tests/reproject/test_constants.py).
// Projected source coordinates are clamped to [-kCoordMargin, Ws + kCoordMargin] (COORD_MARGIN).
constexpr float kCoordMargin = 4.0f;
// Integers up to this are exact in float32; larger images leave the vector path (F32_EXACT_INT).
constexpr int64_t kF32ExactInt = int64_t(1) << 24;
// The plane test's slope scaling 1 / (kPlaneBase + kPlaneSlope * |n.v|) and its smallest usable |n|²
// (PLANE_BASE, PLANE_SLOPE, PLANE_MIN_NORMAL2).
constexpr float kPlaneBase = 0.05f;
constexpr float kPlaneSlope = 0.95f;
constexpr float kPlaneMinNormal2 = 0.25f;
constexpr float kInf = std::numeric_limits<float>::infinity();

// ---- shape checks (the Python layer checks first; these guard direct calls) ---------------------------------
template <class A>
void expect_shape(const A &a, const char *name, std::initializer_list<int64_t> want) {
    if (a.ndim() != want.size())
        throw std::invalid_argument(std::string("reproject: ") + name + " must be " + std::to_string(want.size()) +
                                    "-D, got " + std::to_string(a.ndim()) + "-D");
    size_t d = 0;
    for (int64_t w : want) {
        if (w >= 0 && (int64_t)a.shape(d) != w)
            throw std::invalid_argument(std::string("reproject: ") + name + " has size " +
                                        std::to_string(a.shape(d)) + " in dim " + std::to_string(d) +
                                        ", expected " + std::to_string(w));
        ++d;
    }
}

// ---- float16 (IEEE binary16, held as its bits) ------------------------------------------------------------
// Portable scalar conversions that give the results of the F16C instructions of the vector path (vcvtph2ps, and
// vcvtps2ph with round-to-nearest-even), so that a pixel comes out the same in either path: widening is exact;
// narrowing rounds to nearest, ties to even (subnormals included), overflows to ±inf from 65520 (the midpoint of
// 65504 and 2^16) on, and keeps a NaN's sign and top payload bits with the quiet bit set.
inline float half_to_float(uint16_t h) {
    const uint32_t sign = uint32_t(h & 0x8000u) << 16, exp = (h >> 10) & 0x1fu, man = h & 0x3ffu;
    uint32_t bits;
    if (exp == 0x1fu) {  // inf, NaN (quieted)
        bits = sign | 0x7f800000u | (man << 13) | (man ? 0x400000u : 0u);
    } else if (exp != 0) {  // normal: rebias 15 -> 127
        bits = sign | ((exp + 112u) << 23) | (man << 13);
    } else if (man == 0) {  // ±0
        bits = sign;
    } else {  // subnormal man·2^-24: shift the leading one into the implicit bit
        uint32_t m = man, e = 113u;
        while (!(m & 0x400u)) m <<= 1, --e;
        bits = sign | (e << 23) | ((m & 0x3ffu) << 13);
    }
    float f;
    std::memcpy(&f, &bits, 4);
    return f;
}

inline uint16_t float_to_half(float f) {
    uint32_t x;
    std::memcpy(&x, &f, 4);
    const uint16_t sign = uint16_t((x >> 16) & 0x8000u);
    const uint32_t ax = x & 0x7fffffffu;
    if (ax > 0x7f800000u) return sign | 0x7e00u | uint16_t((ax >> 13) & 0x3ffu);  // NaN
    if (ax >= 0x477ff000u) return sign | 0x7c00u;                                // >= 65520, inf: ±inf
    if (ax >= 0x38800000u)  // >= 2^-14, a normal half: round the mantissa at bit 13 (a carry bumps the exponent)
        return sign | uint16_t((ax + 0xfffu + ((ax >> 13) & 1u) - (112u << 23)) >> 13);
    const uint32_t e = ax >> 23;  // a subnormal half k·2^-24 (k = 1024 is the smallest normal), or 0
    if (e < 102u) return sign;    // below 2^-25 (half the smallest subnormal): ±0
    const uint32_t m = (ax & 0x7fffffu) | 0x800000u, s = 126u - e;  // |f| = m·2^(e-150) = (m >> s)·2^-24 + rest
    const uint32_t k = m >> s, rem = m & ((1u << s) - 1u), halfway = 1u << (s - 1u);
    return sign | uint16_t(k + ((rem > halfway) | ((rem == halfway) & (k & 1u))));
}

// An image plane of float32 or float16 elements (one dtype per plane). Offsets count elements.
struct Plane {
    const void *data = nullptr;
    bool half = false;
    const float *f32() const { return static_cast<const float *>(data); }
    const uint16_t *f16() const { return static_cast<const uint16_t *>(data); }
    float operator[](int64_t i) const { return half ? half_to_float(f16()[i]) : f32()[i]; }
    Plane operator+(int64_t off) const {
        return {half ? static_cast<const void *>(f16() + off) : static_cast<const void *>(f32() + off), half};
    }
};

struct OutPlane {
    void *data = nullptr;
    bool half = false;
    float *f32() const { return static_cast<float *>(data); }
    uint16_t *f16() const { return static_cast<uint16_t *>(data); }
    void set(int64_t i, float v) const {
        if (half)
            f16()[i] = float_to_half(v);
        else
            f32()[i] = v;
    }
    OutPlane operator+(int64_t off) const {
        return {half ? static_cast<void *>(f16() + off) : static_cast<void *>(f32() + off), half};
    }
};

// float16 when the array is float16, float32 when it is float32; TypeError for any other dtype.
bool is_half(const nb::dlpack::dtype &dt, const char *name) {
    if (dt == nb::dtype<float>()) return false;
    if (dt.code == (uint8_t)nb::dlpack::dtype_code::Float && dt.bits == 16 && dt.lanes == 1) return true;
    throw nb::type_error((std::string("reproject: ") + name + " must be float32 or float16").c_str());
}
Plane plane_of(const CA &a, const char *name) { return {a.data(), is_half(a.dtype(), name)}; }
OutPlane plane_of(const OA &a, const char *name) { return {a.data(), is_half(a.dtype(), name)}; }

// What a kernel instantiation knows of the input planes' dtypes, per group (value planes, depths, normals): all
// float32, all float16, or ANY (each plane's own flag, tested at run time: the mixed layouts). The common layouts
// get their own instantiations, so their loads carry no dtype tests (dispatch()).
enum Kind : int { F32, F16, ANY };
template <int VALUES, int DEPTH, int NORMALS>
struct Layout {
    static constexpr int values = VALUES, depth = DEPTH, normals = NORMALS;
};
template <int K>
inline bool halfp(const Plane &p) {
    return K == F16 || (K == ANY && p.half);
}
template <int K>
SR_INLINE float load(const Plane &p, int64_t i) {
    return halfp<K>(p) ? half_to_float(p.f16()[i]) : p.f32()[i];
}

// ---- per-batch-item inputs ---------------------------------------------------------------------------------
struct Camera {  // row-major 3x3 matrices, composed in Python
    const float *P, *kt, *M, *t, *Ki;
    const float *R;  // rotation of the source camera (its cam_from_world): world motion, plane test; else nullptr
};

struct Source {  // one batch item of the source view
    Plane chan[kMaxStackChannels];  // value planes (history colour and length may live in two arrays)
    Plane depth, n0, n1, n2;
    int64_t C, Hs, Ws;
};

struct Dest {  // one batch item of the destination view
    Plane depth, n0, n1, n2;
    Plane mo0, mo1;       // screen motion to the source instant (x, y in pixels), when motion
    Plane mw0, mw1, mw2;  // world motion of the surface point to the source instant, when world
    bool motion = false, world = false;
    int64_t H, W;
};

struct Tests {
    float pos_thr2, nrm_thr2;
    bool cubic = false;  // sampling="catmull_rom" (on the bilinear pass): cubic_row after each row
    bool plane = false;  // position_test="plane": the plane test instead of the distance test
};

inline bool finitef(float x) { return std::isfinite(x); }

// The plane test's terms of one destination pixel (see the notes at the top).
struct PlaneTerms {
    float nc0 = 0.0f, nc1 = 0.0f, nc2 = 0.0f, thr2 = -1.0f;
};

SR_INLINE void plane_terms(const Camera &cam, const Tests &th, float uc, float vc, float z, float n0, float n1,
                           float n2, PlaneTerms &pl) {
    const float nn = (n0 * n0 + n1 * n1) + n2 * n2;
    const bool usable = (nn >= kPlaneMinNormal2) & (nn < kInf);
    if (!usable) n0 = n1 = n2 = 0.0f;
    const float *R = cam.R, *M = cam.M;
    pl.nc0 = (R[0] * n0 + R[1] * n1) + R[2] * n2;
    pl.nc1 = (R[3] * n0 + R[4] * n1) + R[5] * n2;
    pl.nc2 = (R[6] * n0 + R[7] * n1) + R[8] * n2;
    const float r0 = (M[0] * uc + M[1] * vc) + M[2];
    const float r1 = (M[3] * uc + M[4] * vc) + M[5];
    const float r2 = (M[6] * uc + M[7] * vc) + M[8];
    const float nv = (pl.nc0 * r0 + pl.nc1 * r1) + pl.nc2 * r2;
    const float rr = (r0 * r0 + r1 * r1) + r2 * r2;
    const float cosine = std::fabs(nv) / std::sqrt(rr);
    const float scale = z / (kPlaneBase + kPlaneSlope * cosine);
    pl.thr2 = usable ? th.pos_thr2 * (scale * scale) : -1.0f;
}

// One tap at integer source pixel (xi, yi) with bilinear weight w > 0. Returns its reason code; accumulates the
// weighted values into num / den when it passes every test. q: destination point in the source frame; nd: the
// destination normal (sanitised).
template <int NC, class L>
SR_INLINE uint8_t tap(const Source &s, const Camera &cam, const Tests &th, float xi, float yi, float w, float qx,
                      float qy, float qz, float nd0, float nd1, float nd2, const PlaneTerms &pl, float &den,
                      float *num) {
    const bool in_frame = (xi >= 0.0f) & (xi <= (float)(s.Ws - 1)) & (yi >= 0.0f) & (yi <= (float)(s.Hs - 1));
    if (!in_frame) return OUT_OF_FRAME;
    const int64_t idx = (int64_t)yi * s.Ws + (int64_t)xi;
    const int64_t C = NC > 0 ? NC : s.C;
    // finite values: the channel sum is finite (any NaN/Inf makes it non-finite), summed in channel order
    float vals[NC > 0 ? NC : kMaxStackChannels];
    float vsum = 0.0f;
    for (int64_t c = 0; c < C; ++c) {
        vals[c] = load<L::values>(s.chan[c], idx);
        vsum += vals[c];
    }
    const bool finite = finitef(vsum);
    const float zr = load<L::depth>(s.depth, idx);
    const bool src_ok = finitef(zr) & (zr > 0.0f);
    const float zs = src_ok ? zr : 1.0f;
    float m0 = load<L::normals>(s.n0, idx), m1 = load<L::normals>(s.n1, idx), m2 = load<L::normals>(s.n2, idx);
    m0 = finitef(m0) ? m0 : 0.0f;
    m1 = finitef(m1) ? m1 : 0.0f;
    m2 = finitef(m2) ? m2 : 0.0f;
    const float ut = xi + 0.5f, vt = yi + 0.5f;
    const float px = zs * ((cam.Ki[0] * ut + cam.Ki[1] * vt) + cam.Ki[2]);
    const float py = zs * (cam.Ki[4] * vt + cam.Ki[5]);
    const float dx = qx - px, dy = qy - py, dz = qz - zs;
    const float dp2 = (dx * dx + dy * dy) + dz * dz;
    const float e0 = m0 - nd0, e1 = m1 - nd1, e2 = m2 - nd2;
    const float dn2 = (e0 * e0 + e1 * e1) + e2 * e2;
    bool pos_ok;
    if (th.plane) {
        const float dist = (pl.nc0 * dx + pl.nc1 * dy) + pl.nc2 * dz;
        pos_ok = dist * dist <= pl.thr2;
    } else {
        pos_ok = dp2 <= th.pos_thr2;
    }
    const bool nrm_ok = dn2 <= th.nrm_thr2;
    // first failing test, in the order of the torch code's overrides
    const uint8_t code = !src_ok ? NO_SURFACE_SRC : !pos_ok ? POSITION : !nrm_ok ? NORMAL : !finite ? NONFINITE : KEPT;
    if (code == KEPT) {
        den += w;
        for (int64_t c = 0; c < C; ++c) num[c] += w * vals[c];
    }
    return code;
}

// Motion vectors of destination pixel p (uc, vc its centre): the source coordinates (u, v) = centre + motion, or
// the lower clamp where the motion (or world motion) is not finite; the point q moved by R_src · world motion
// (zero where not finite), q + ((R[i,0]*m0 + R[i,1]*m1) + R[i,2]*m2). Returns the moved point's z > 0 (false:
// BEHIND_CAMERA), as the torch reference's _motion_source.
SR_INLINE bool motion_source(const Dest &d, const Camera &cam, int64_t p, float uc, float vc, float &qx, float &qy,
                             float &qz, float &u, float &v) {
    const float m0 = d.mo0[p], m1 = d.mo1[p];
    bool ok = finitef(m0) & finitef(m1);
    if (d.world) {
        float w0 = d.mw0[p], w1 = d.mw1[p], w2 = d.mw2[p];
        ok = ok & finitef(w0) & finitef(w1) & finitef(w2);
        if (!ok) w0 = w1 = w2 = 0.0f;
        const float *R = cam.R;
        qx = qx + ((R[0] * w0 + R[1] * w1) + R[2] * w2);
        qy = qy + ((R[3] * w0 + R[4] * w1) + R[5] * w2);
        qz = qz + ((R[6] * w0 + R[7] * w1) + R[8] * w2);
    }
    u = ok ? uc + m0 : -kCoordMargin;
    v = ok ? vc + m1 : -kCoordMargin;
    return (qz > 0.0f) & finitef(u) & finitef(v);
}

// Where a row's results go: C value rows, confidence, reason and valid (one byte, 0/1), each W long.
struct RowOut {
    OutPlane num[kMaxStackChannels];
    float *den;
    uint8_t *reason;
    uint8_t *valid;
};

// The projection of destination pixel (x, y) into the source: KEPT with the source coordinates (u, v) (clamped),
// the destination point q in the source frame, its sanitised normal nd and (plane test) its plane terms, or the
// reason it reads no tap.
template <class L>
SR_INLINE uint8_t project_pixel(const Source &s, const Dest &d, const Camera &cam, const Tests &th, int64_t x,
                                int64_t y, float &qx, float &qy, float &qz, float &u, float &v, float &nd0,
                                float &nd1, float &nd2, PlaneTerms &pl) {
    const int64_t p = y * d.W + x;
    const float zr = load<L::depth>(d.depth, p);
    if (!(finitef(zr) & (zr > 0.0f))) return NO_SURFACE_DST;
    const float uc = (float)x + 0.5f, vc = (float)y + 0.5f;
    const float *M = cam.M, *t = cam.t;
    qx = ((M[0] * uc + M[1] * vc) + M[2]) * zr + t[0];
    qy = ((M[3] * uc + M[4] * vc) + M[5]) * zr + t[1];
    qz = ((M[6] * uc + M[7] * vc) + M[8]) * zr + t[2];
    if (d.motion) {  // the source position from the motion vectors, the point moved with the world motion
        if (!motion_source(d, cam, p, uc, vc, qx, qy, qz, u, v)) return BEHIND_CAMERA;
    } else {
        const float inv_z = 1.0f / zr;
        const float *P = cam.P, *kt = cam.kt;
        const float wx = ((P[0] * uc + P[1] * vc) + P[2]) + kt[0] * inv_z;
        const float wy = ((P[3] * uc + P[4] * vc) + P[5]) + kt[1] * inv_z;
        const float wz = ((P[6] * uc + P[7] * vc) + P[8]) + kt[2] * inv_z;
        if (!(wz > 0.0f)) return BEHIND_CAMERA;
        u = wx / wz, v = wy / wz;
        if (!(finitef(u) & finitef(v))) return BEHIND_CAMERA;
    }
    u = std::min(std::max(u, -kCoordMargin), (float)s.Ws + kCoordMargin);
    v = std::min(std::max(v, -kCoordMargin), (float)s.Hs + kCoordMargin);
    nd0 = load<L::normals>(d.n0, p), nd1 = load<L::normals>(d.n1, p), nd2 = load<L::normals>(d.n2, p);
    if (th.plane) plane_terms(cam, th, uc, vc, zr, nd0, nd1, nd2, pl);
    nd0 = finitef(nd0) ? nd0 : 0.0f;
    nd1 = finitef(nd1) ? nd1 : 0.0f;
    nd2 = finitef(nd2) ? nd2 : 0.0f;
    return KEPT;
}

// Warp one destination pixel (x, y); writes its results at position x of the row outputs.
template <int NC, bool BILINEAR, class L>
inline void warp_pixel(const Source &s, const Dest &d, const Camera &cam, const Tests &th, int64_t x, int64_t y,
                       const RowOut &o) {
    const int64_t C = NC > 0 ? NC : s.C;
    float num[NC > 0 ? NC : kMaxStackChannels];
    for (int64_t c = 0; c < C; ++c) num[c] = 0.0f;
    auto invalid = [&](uint8_t reason, float den) {
        for (int64_t c = 0; c < C; ++c) o.num[c].set(x, 0.0f);
        o.den[x] = den;
        o.reason[x] = reason;
        o.valid[x] = 0;
    };
    float qx, qy, qz, u, v, nd0, nd1, nd2;
    PlaneTerms pl;
    const uint8_t projected = project_pixel<L>(s, d, cam, th, x, y, qx, qy, qz, u, v, nd0, nd1, nd2, pl);
    if (projected != KEPT) return invalid(projected, 0.0f);

    float den = 0.0f;
    uint8_t worst = KEPT;  // max code over taps of non-zero weight; zero-weight taps contribute nothing at all
    if (BILINEAR) {
        const float fxs = u - 0.5f, fys = v - 0.5f;
        const float x0 = std::floor(fxs), y0 = std::floor(fys);
        const float fx = fxs - x0, fy = fys - y0;
        const float x1 = x0 + 1.0f, y1 = y0 + 1.0f;
        const float w[4] = {(1.0f - fx) * (1.0f - fy), fx * (1.0f - fy), (1.0f - fx) * fy, fx * fy};
        const float xs[4] = {x0, x1, x0, x1}, ys[4] = {y0, y0, y1, y1};
        for (int k = 0; k < 4; ++k) {
            if (!(w[k] > 0.0f)) continue;
            const uint8_t code =
                tap<NC, L>(s, cam, th, xs[k], ys[k], w[k], qx, qy, qz, nd0, nd1, nd2, pl, den, num);
            worst = std::max(worst, code);
        }
    } else {
        worst = tap<NC, L>(s, cam, th, std::floor(u), std::floor(v), 1.0f, qx, qy, qz, nd0, nd1, nd2, pl, den, num);
    }
    if (!(den > 0.0f)) return invalid(worst, den);
    for (int64_t c = 0; c < C; ++c) o.num[c].set(x, num[c] / den);
    o.den[x] = den;
    o.reason[x] = KEPT;
    o.valid[x] = 1;
}

// Catmull-Rom weights (a = -0.5) of the taps at offsets -1, 0, 1, 2 from floor(x) for the fraction f, in the
// operation order of stereorepro.reproject._general.catmull_rom_weights.
SR_INLINE void catmull_rom_weights(float f, float w[4]) {
    w[0] = ((-0.5f * f + 1.0f) * f - 0.5f) * f;
    w[1] = (1.5f * f - 2.5f) * f * f + 1.0f;
    w[2] = ((-1.5f * f + 2.0f) * f + 0.5f) * f;
    w[3] = (0.5f * f - 0.5f) * f * f;
}

// sampling="catmull_rom": the valid pixels of a warped row whose 4x4 footprint (columns x0 - 1 .. x0 + 2 around the
// bilinear taps, rows likewise) passes every tap test get the separable Catmull-Rom sum (each row's four columns in
// order, then the rows in order), clamped at 0 per channel; the others keep the bilinear values. The arithmetic of
// stereorepro.reproject._general.catmull_rom_pixels.
template <int NC, class L>
void cubic_row(const Source &s, const Dest &d, const Camera &cam, const Tests &th, int64_t y, const RowOut &o) {
    const int64_t C = NC > 0 ? NC : s.C;
    for (int64_t x = 0; x < d.W; ++x) {
        if (!o.valid[x]) continue;
        float qx, qy, qz, u, v, nd0, nd1, nd2;
        PlaneTerms pl;
        if (project_pixel<L>(s, d, cam, th, x, y, qx, qy, qz, u, v, nd0, nd1, nd2, pl) != KEPT) continue;
        const float fxs = u - 0.5f, fys = v - 0.5f;
        const float x0 = std::floor(fxs), y0 = std::floor(fys);
        float wx[4], wy[4];
        catmull_rom_weights(fxs - x0, wx);
        catmull_rom_weights(fys - y0, wy);
        float total[NC > 0 ? NC : kMaxStackChannels];
        bool all = true;
        for (int j = 0; j < 4 && all; ++j) {
            float row[NC > 0 ? NC : kMaxStackChannels];
            for (int64_t c = 0; c < C; ++c) row[c] = 0.0f;
            const float yi = y0 + (float)(j - 1);
            for (int i = 0; i < 4 && all; ++i) {
                float den = 0.0f;
                const float xi = x0 + (float)(i - 1);
                all = tap<NC, L>(s, cam, th, xi, yi, wx[i], qx, qy, qz, nd0, nd1, nd2, pl, den, row) == KEPT;
            }
            for (int64_t c = 0; c < C; ++c) total[c] = j == 0 ? wy[0] * row[c] : total[c] + wy[j] * row[c];
        }
        if (!all) continue;
        for (int64_t c = 0; c < C; ++c) o.num[c].set(x, total[c] < 0.0f ? 0.0f : total[c]);
    }
}

#ifdef SR_AVX2_PATH
// ---- AVX2 path: 8 destination pixels at a time, gathers for the taps. Same operations in the same order as the
// scalar path (IEEE mul/add/div/floor are lane-wise identical; target avx2 without fma, so nothing is fused).
// Rejected taps are read at clamped indices (as the torch code does) and masked, so lanes never branch.
namespace v8 {
SR_AVX2 inline __m256 sel(__m256 m, __m256 a, __m256 b) { return _mm256_blendv_ps(b, a, m); }  // m ? a : b
SR_AVX2 inline __m256 isfinite(__m256 x) {
    const __m256 abs = _mm256_and_ps(x, _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff)));
    return _mm256_cmp_ps(abs, _mm256_set1_ps(3.40282347e38f), _CMP_LE_OQ);
}
SR_AVX2 inline __m256 fin0(__m256 x) { return _mm256_and_ps(x, isfinite(x)); }  // non-finite -> +0
SR_AVX2 inline __m256 add(__m256 a, __m256 b) { return _mm256_add_ps(a, b); }
SR_AVX2 inline __m256 sub(__m256 a, __m256 b) { return _mm256_sub_ps(a, b); }
SR_AVX2 inline __m256 mul(__m256 a, __m256 b) { return _mm256_mul_ps(a, b); }
SR_AVX2 inline __m256 set(float a) { return _mm256_set1_ps(a); }
SR_AVX2 inline __m256 band(__m256 a, __m256 b) { return _mm256_and_ps(a, b); }
SR_AVX2 inline __m256 gt(__m256 a, __m256 b) { return _mm256_cmp_ps(a, b, _CMP_GT_OQ); }
SR_AVX2 inline __m256 ge(__m256 a, __m256 b) { return _mm256_cmp_ps(a, b, _CMP_GE_OQ); }
SR_AVX2 inline __m256 le(__m256 a, __m256 b) { return _mm256_cmp_ps(a, b, _CMP_LE_OQ); }
SR_AVX2 inline __m256 lt(__m256 a, __m256 b) { return _mm256_cmp_ps(a, b, _CMP_LT_OQ); }
SR_AVX2 inline __m256 absv(__m256 x) { return _mm256_and_ps(x, _mm256_castsi256_ps(_mm256_set1_epi32(0x7fffffff))); }

// 8 consecutive elements of a plane from element i, widened to float32 (exact).
template <int K = ANY>
SR_AVX2 SR_INLINE __m256 ld8(const Plane &p, int64_t i) {
    if (halfp<K>(p)) return _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i *>(p.f16() + i)));
    return _mm256_loadu_ps(p.f32() + i);
}
// Stores 8 float32 at element i (float16: rounded to nearest, ties to even, as torch's .to(torch.float16)).
SR_AVX2 SR_INLINE void st8(const OutPlane &p, int64_t i, __m256 v) {
    if (p.half)
        _mm_storeu_si128(reinterpret_cast<__m128i *>(p.f16() + i), _mm256_cvtps_ph(v, _MM_FROUND_TO_NEAREST_INT));
    else
        _mm256_storeu_ps(p.f32() + i, v);
}
// 8 float16 elements at indices ix, widened: scalar 16-bit loads (pinsrw; no 16-bit gather in AVX2, and a 32-bit
// gather could read past the plane's end).
SR_AVX2 SR_INLINE __m256 gather16(const uint16_t *h, const int32_t *ix) {
    __m128i v = _mm_cvtsi32_si128(h[ix[0]]);
    v = _mm_insert_epi16(v, h[ix[1]], 1);
    v = _mm_insert_epi16(v, h[ix[2]], 2);
    v = _mm_insert_epi16(v, h[ix[3]], 3);
    v = _mm_insert_epi16(v, h[ix[4]], 4);
    v = _mm_insert_epi16(v, h[ix[5]], 5);
    v = _mm_insert_epi16(v, h[ix[6]], 6);
    v = _mm_insert_epi16(v, h[ix[7]], 7);
    return _mm256_cvtph_ps(v);
}

struct Consts {
    __m256 Ki0, Ki1, Ki2, Ki4, Ki5, wm1, wm2, hm1, thr_p, thr_n;
    __m256i Wsi;
    bool plane;  // the plane test (per-pixel terms in Pixels8)
};

// 8 destination pixels projected into the source camera (the scalar warp_pixel's arithmetic).
struct Pixels8 {
    __m256 dst_ok, front, pixel_ok;  // masks: a surface; in front of the source camera with finite (u, v); both
    __m256 u, v;                     // source coordinates, clamped (the lower clamp where not front)
    __m256 qx, qy, qz;               // the destination point in the source camera frame
    __m256 nd0, nd1, nd2;            // the destination normal, non-finite components 0
    __m256 nc0, nc1, nc2, thr2;      // plane test: the normal in the source camera's axes, the squared threshold
};

// Source data at 8 taps: C value channels, depth and normal.
template <int NC>
struct Taps {
    __m256 vals[NC > 0 ? NC : kMaxStackChannels];
    __m256 z, n0, n1, n2;
};

// 8 taps at clamped (xi, yi): 8-lane gathers.
template <int NC, class L>
SR_AVX2 SR_INLINE void gather_taps(const Source &s, const Consts &k, __m256 xi, __m256 yi, Taps<NC> &t) {
    const int64_t C = NC > 0 ? NC : s.C;
    const __m256 zero = _mm256_setzero_ps();
    const __m256i xc = _mm256_cvttps_epi32(_mm256_min_ps(_mm256_max_ps(xi, zero), k.wm1));
    const __m256i yc = _mm256_cvttps_epi32(_mm256_min_ps(_mm256_max_ps(yi, zero), k.hm1));
    const __m256i idx = _mm256_add_epi32(_mm256_mullo_epi32(yc, k.Wsi), xc);
    alignas(32) int32_t ix[8];
    if (L::values != F32 || L::depth != F32 || L::normals != F32)
        _mm256_store_si256(reinterpret_cast<__m256i *>(ix), idx);
    auto gather = [&](const Plane &p, auto kind) SR_AVX2 SR_LAMBDA_INLINE {
        return halfp<decltype(kind)::value>(p) ? gather16(p.f16(), ix) : _mm256_i32gather_ps(p.f32(), idx, 4);
    };
    using KV = std::integral_constant<int, L::values>;
    using KZ = std::integral_constant<int, L::depth>;
    using KN = std::integral_constant<int, L::normals>;
    for (int64_t c = 0; c < C; ++c) t.vals[c] = gather(s.chan[c], KV{});
    t.z = gather(s.depth, KZ{});
    t.n0 = gather(s.n0, KN{});
    t.n1 = gather(s.n1, KN{});
    t.n2 = gather(s.n2, KN{});
}

// The horizontally adjacent taps (x0, yi) and (x0 + 1, yi) of 8 pixels with one 64-bit load per pixel and plane
// (half the gathered elements). Needs Ws >= 2. The pair starts at xp = clamp(x0, 0, Ws - 2); where x0 = Ws - 1 the
// x0 tap is the pair's second element, where x0 = -1 the x0 + 1 tap is its first; other out-of-frame taps read
// some in-frame pixel and are masked by the caller. A float16 pair is one 32-bit load (cheaper than an 8-lane
// 32-bit gather of the pairs).
template <int NC, class L>
SR_AVX2 SR_INLINE void gather_pairs(const Source &s, const Consts &k, __m256 x0, __m256 yi, Taps<NC> &a,
                                    Taps<NC> &b) {
    const int64_t C = NC > 0 ? NC : s.C;
    const __m256 zero = _mm256_setzero_ps();
    const __m256i xp = _mm256_cvttps_epi32(_mm256_min_ps(_mm256_max_ps(x0, zero), k.wm2));
    const __m256i yc = _mm256_cvttps_epi32(_mm256_min_ps(_mm256_max_ps(yi, zero), k.hm1));
    const __m256i idx = _mm256_add_epi32(_mm256_mullo_epi32(yc, k.Wsi), xp);
    alignas(32) int32_t ix[8];
    _mm256_store_si256(reinterpret_cast<__m256i *>(ix), idx);
    const __m256 a_from_b = _mm256_cmp_ps(x0, k.wm2, _CMP_GT_OQ);   // x0 = Ws - 1
    const __m256 b_from_a = _mm256_cmp_ps(x0, zero, _CMP_LT_OQ);    // x0 = -1
    const bool edge = _mm256_movemask_ps(_mm256_or_ps(a_from_b, b_from_a)) != 0;
    // Scalar 8-byte loads (two adjacent floats each; the 8 indices are extracted once for all planes) are cheaper
    // than 8-lane gathers.
    auto load = [&](const Plane &p, auto kind, __m256 &va, __m256 &vb) SR_AVX2 SR_LAMBDA_INLINE {
        __m256 ea, eb;
        if (halfp<decltype(kind)::value>(p)) {
            // one 4-byte load per pixel: the halves a_l, b_l; de-interleaved, then widened
            const uint16_t *plane = p.f16();
            auto pair = [&](int l) SR_LAMBDA_INLINE {
                int32_t v;
                std::memcpy(&v, plane + ix[l], 4);
                return v;
            };
            const __m128i deint = _mm_setr_epi8(0, 1, 4, 5, 8, 9, 12, 13, 2, 3, 6, 7, 10, 11, 14, 15);
            const __m128i q0 = _mm_shuffle_epi8(_mm_setr_epi32(pair(0), pair(1), pair(2), pair(3)), deint);
            const __m128i q1 = _mm_shuffle_epi8(_mm_setr_epi32(pair(4), pair(5), pair(6), pair(7)), deint);
            ea = _mm256_cvtph_ps(_mm_unpacklo_epi64(q0, q1));  // a0 .. a7
            eb = _mm256_cvtph_ps(_mm_unpackhi_epi64(q0, q1));  // b0 .. b7
        } else {
            // movq / movhpd of two adjacent floats (intrinsics whose pointers may alias float data)
            const float *plane = p.f32();
            auto lo = [&](int l) {
                return _mm_castsi128_pd(_mm_loadl_epi64(reinterpret_cast<const __m128i *>(plane + ix[l])));
            };
            auto hi = [&](__m128d q, int l) {
                return _mm_loadh_pd(q, reinterpret_cast<const double *>(plane + ix[l]));
            };
            const __m128d q0 = hi(lo(0), 1), q1 = hi(lo(2), 3), q2 = hi(lo(4), 5), q3 = hi(lo(6), 7);  // a0 b0 a1 ..
            const __m256 g0 = _mm256_castpd_ps(_mm256_set_m128d(q1, q0));  // a0 b0 a1 b1 | a2 b2 a3 b3
            const __m256 g1 = _mm256_castpd_ps(_mm256_set_m128d(q3, q2));  // a4 b4 a5 b5 | a6 b6 a7 b7
            ea = _mm256_castpd_ps(_mm256_permute4x64_pd(
                _mm256_castps_pd(_mm256_shuffle_ps(g0, g1, _MM_SHUFFLE(2, 0, 2, 0))), _MM_SHUFFLE(3, 1, 2, 0)));
            eb = _mm256_castpd_ps(_mm256_permute4x64_pd(
                _mm256_castps_pd(_mm256_shuffle_ps(g0, g1, _MM_SHUFFLE(3, 1, 3, 1))), _MM_SHUFFLE(3, 1, 2, 0)));
        }
        if (edge) {
            va = sel(a_from_b, eb, ea);
            vb = sel(b_from_a, ea, eb);
        } else {
            va = ea;
            vb = eb;
        }
    };
    using KV = std::integral_constant<int, L::values>;
    using KZ = std::integral_constant<int, L::depth>;
    using KN = std::integral_constant<int, L::normals>;
    for (int64_t c = 0; c < C; ++c) load(s.chan[c], KV{}, a.vals[c], b.vals[c]);
    load(s.depth, KZ{}, a.z, b.z);
    load(s.n0, KN{}, a.n0, b.n0);
    load(s.n1, KN{}, a.n1, b.n1);
    load(s.n2, KN{}, a.n2, b.n2);
}

// Accept tests and accumulation of 8 taps at (xi, yi) with weights w (see the scalar tap()). With CODES, also the
// running max of the taps' reason codes (worst); warp_row() asks for them only where a pixel kept nothing.
template <int NC, bool CODES>
SR_AVX2 SR_INLINE void tap(const Source &s, const Consts &k, const Taps<NC> &g, __m256 xi, __m256 yi, __m256 w,
                           const Pixels8 &pix, __m256 &den, __m256 *num, __m256 &worst) {
    const __m256 pixel_ok = pix.pixel_ok, qx = pix.qx, qy = pix.qy, qz = pix.qz, nd0 = pix.nd0, nd1 = pix.nd1,
                 nd2 = pix.nd2;
    const int64_t C = NC > 0 ? NC : s.C;
    const __m256 zero = _mm256_setzero_ps(), one = set(1.0f);
    const __m256 in_frame = band(band(ge(xi, zero), le(xi, k.wm1)), band(ge(yi, zero), le(yi, k.hm1)));
    __m256 vsum = zero;
    for (int64_t c = 0; c < C; ++c) vsum = add(vsum, g.vals[c]);
    const __m256 finite = isfinite(vsum);
    const __m256 src_ok = band(isfinite(g.z), gt(g.z, zero));
    const __m256 zs = sel(src_ok, g.z, one);
    const __m256 m0 = fin0(g.n0), m1 = fin0(g.n1), m2 = fin0(g.n2);
    const __m256 ut = add(xi, set(0.5f)), vt = add(yi, set(0.5f));
    const __m256 px = mul(zs, add(add(mul(k.Ki0, ut), mul(k.Ki1, vt)), k.Ki2));
    const __m256 py = mul(zs, add(mul(k.Ki4, vt), k.Ki5));
    const __m256 dx = sub(qx, px), dy = sub(qy, py), dz = sub(qz, zs);
    const __m256 dp2 = add(add(mul(dx, dx), mul(dy, dy)), mul(dz, dz));
    const __m256 e0 = sub(m0, nd0), e1 = sub(m1, nd1), e2 = sub(m2, nd2);
    const __m256 dn2 = add(add(mul(e0, e0), mul(e1, e1)), mul(e2, e2));
    __m256 pos_ok;
    if (k.plane) {
        const __m256 dist = add(add(mul(pix.nc0, dx), mul(pix.nc1, dy)), mul(pix.nc2, dz));
        pos_ok = le(mul(dist, dist), pix.thr2);
    } else {
        pos_ok = le(dp2, k.thr_p);
    }
    const __m256 nrm_ok = le(dn2, k.thr_n);
    if constexpr (CODES) {  // first failing test, as the scalar tap()
        __m256 code = sel(finite, zero, set(NONFINITE));
        code = sel(nrm_ok, code, set(NORMAL));
        code = sel(pos_ok, code, set(POSITION));
        code = sel(src_ok, code, set(NO_SURFACE_SRC));
        const __m256 wpos = gt(w, zero);
        code = sel(band(in_frame, wpos), code, band(wpos, set(OUT_OF_FRAME)));
        worst = _mm256_max_ps(worst, code);
    }
    const __m256 hard = band(band(band(pixel_ok, in_frame), band(src_ok, finite)), band(pos_ok, nrm_ok));
    const __m256 ws = band(w, hard);  // w or +0, as w * hard.float() in torch
    den = add(den, ws);
    for (int64_t c = 0; c < C; ++c) num[c] = add(num[c], mul(ws, band(g.vals[c], finite)));
}

// The camera of a batch item broadcast to 8 lanes, and the per-row constants of the tap tests.
struct Warp8 {
    __m256 P[9], M[9], kt[3], t[3];
    __m256 R[9];  // rotation of the source camera (world motion, plane test)
    __m256 umax, vmax;  // upper clamps of the source coordinates
    __m256 thr_p2;  // the squared position threshold (plane test)
    bool plane;
};

SR_AVX2 SR_INLINE void broadcast_camera(const Source &s, const Camera &cam, const Tests &th, Warp8 &w, Consts &k) {
    for (int i = 0; i < 9; ++i) w.P[i] = set(cam.P[i]), w.M[i] = set(cam.M[i]);
    for (int i = 0; i < 3; ++i) w.kt[i] = set(cam.kt[i]), w.t[i] = set(cam.t[i]);
    if (cam.R)
        for (int i = 0; i < 9; ++i) w.R[i] = set(cam.R[i]);
    w.umax = set((float)s.Ws + kCoordMargin), w.vmax = set((float)s.Hs + kCoordMargin);
    k.Ki0 = set(cam.Ki[0]), k.Ki1 = set(cam.Ki[1]), k.Ki2 = set(cam.Ki[2]), k.Ki4 = set(cam.Ki[4]);
    k.Ki5 = set(cam.Ki[5]);
    k.wm1 = set((float)(s.Ws - 1)), k.wm2 = set((float)(s.Ws - 2)), k.hm1 = set((float)(s.Hs - 1));
    k.thr_p = set(th.pos_thr2), k.thr_n = set(th.nrm_thr2);
    k.Wsi = _mm256_set1_epi32((int32_t)s.Ws);
    k.plane = w.plane = th.plane;
    w.thr_p2 = set(th.pos_thr2);
}

// The plane terms of 8 pixels: the scalar plane_terms() lane by lane (z sanitised, raw normals n).
SR_AVX2 SR_INLINE void plane8(const Warp8 &w, __m256 uc, __m256 vc, __m256 z, __m256 n0, __m256 n1, __m256 n2,
                              Pixels8 &px) {
    const __m256 nn = add(add(mul(n0, n0), mul(n1, n1)), mul(n2, n2));
    const __m256 usable = band(ge(nn, set(kPlaneMinNormal2)), lt(nn, set(kInf)));
    n0 = band(n0, usable), n1 = band(n1, usable), n2 = band(n2, usable);
    const __m256 *R = w.R, *M = w.M;
    px.nc0 = add(add(mul(R[0], n0), mul(R[1], n1)), mul(R[2], n2));
    px.nc1 = add(add(mul(R[3], n0), mul(R[4], n1)), mul(R[5], n2));
    px.nc2 = add(add(mul(R[6], n0), mul(R[7], n1)), mul(R[8], n2));
    const __m256 r0 = add(add(mul(M[0], uc), mul(M[1], vc)), M[2]);
    const __m256 r1 = add(add(mul(M[3], uc), mul(M[4], vc)), M[5]);
    const __m256 r2 = add(add(mul(M[6], uc), mul(M[7], vc)), M[8]);
    const __m256 nv = add(add(mul(px.nc0, r0), mul(px.nc1, r1)), mul(px.nc2, r2));
    const __m256 rr = add(add(mul(r0, r0), mul(r1, r1)), mul(r2, r2));
    const __m256 cosine = _mm256_div_ps(absv(nv), _mm256_sqrt_ps(rr));
    const __m256 scale = _mm256_div_ps(z, add(set(kPlaneBase), mul(set(kPlaneSlope), cosine)));
    px.thr2 = sel(usable, mul(w.thr_p2, mul(scale, scale)), set(-1.0f));
}

template <class L>
SR_AVX2 SR_INLINE void project8(const Dest &d, const Warp8 &w, int64_t p, __m256 uc, __m256 vc, Pixels8 &px) {
    const __m256 zero = _mm256_setzero_ps(), one = set(1.0f), lo = set(-kCoordMargin);
    const __m256 zr = ld8<L::depth>(d.depth, p);
    px.dst_ok = band(isfinite(zr), gt(zr, zero));
    const __m256 z = sel(px.dst_ok, zr, one);
    const __m256 *P = w.P, *M = w.M, *kt = w.kt, *t = w.t;
    px.qx = add(mul(add(add(mul(M[0], uc), mul(M[1], vc)), M[2]), z), t[0]);
    px.qy = add(mul(add(add(mul(M[3], uc), mul(M[4], vc)), M[5]), z), t[1]);
    px.qz = add(mul(add(add(mul(M[6], uc), mul(M[7], vc)), M[8]), z), t[2]);
    __m256 u, v, front;
    if (d.motion) {  // motion_source() of the scalar path
        const __m256 m0 = ld8(d.mo0, p), m1 = ld8(d.mo1, p);
        __m256 ok = band(isfinite(m0), isfinite(m1));
        if (d.world) {
            __m256 w0 = ld8(d.mw0, p), w1 = ld8(d.mw1, p), w2 = ld8(d.mw2, p);
            ok = band(ok, band(isfinite(w0), band(isfinite(w1), isfinite(w2))));
            w0 = band(w0, ok), w1 = band(w1, ok), w2 = band(w2, ok);
            const __m256 *R = w.R;
            px.qx = add(px.qx, add(add(mul(R[0], w0), mul(R[1], w1)), mul(R[2], w2)));
            px.qy = add(px.qy, add(add(mul(R[3], w0), mul(R[4], w1)), mul(R[5], w2)));
            px.qz = add(px.qz, add(add(mul(R[6], w0), mul(R[7], w1)), mul(R[8], w2)));
        }
        u = sel(ok, add(uc, m0), lo);
        v = sel(ok, add(vc, m1), lo);
        front = gt(px.qz, zero);
    } else {
        const __m256 inv_z = _mm256_div_ps(one, z);
        const __m256 wx = add(add(add(mul(P[0], uc), mul(P[1], vc)), P[2]), mul(kt[0], inv_z));
        const __m256 wy = add(add(add(mul(P[3], uc), mul(P[4], vc)), P[5]), mul(kt[1], inv_z));
        __m256 wz = add(add(add(mul(P[6], uc), mul(P[7], vc)), P[8]), mul(kt[2], inv_z));
        front = gt(wz, zero);
        wz = sel(front, wz, one);
        u = _mm256_div_ps(wx, wz), v = _mm256_div_ps(wy, wz);
    }
    front = band(front, band(isfinite(u), isfinite(v)));
    px.front = front;
    px.u = _mm256_min_ps(_mm256_max_ps(sel(front, u, lo), lo), w.umax);
    px.v = _mm256_min_ps(_mm256_max_ps(sel(front, v, lo), lo), w.vmax);
    const __m256 n0 = ld8<L::normals>(d.n0, p), n1 = ld8<L::normals>(d.n1, p), n2 = ld8<L::normals>(d.n2, p);
    if (w.plane)
        plane8(w, uc, vc, z, n0, n1, n2, px);
    else
        px.nc0 = px.nc1 = px.nc2 = px.thr2 = zero;  // unread (the distance test)
    px.nd0 = fin0(n0);
    px.nd1 = fin0(n1);
    px.nd2 = fin0(n2);
    px.pixel_ok = band(px.dst_ok, front);
}

// What the taps of 8 pixels accumulate: the accepted weight, the weighted values and (with codes) the worst code.
template <int NC>
struct Sums8 {
    __m256 den, worst;
    __m256 num[NC > 0 ? NC : kMaxStackChannels];
};

// All taps of 8 pixels (ok_bits: the lanes with pixel_ok): accumulates den / num and, with CODES, the worst code.
template <int NC, bool BILINEAR, bool CODES, class L>
SR_AVX2 SR_INLINE void taps8(const Source &s, const Consts &k, const Pixels8 &px, int ok_bits, Taps<NC> &ga,
                             Taps<NC> &gb, Sums8<NC> &acc) {
    const int64_t C = NC > 0 ? NC : s.C;
    const __m256 zero = _mm256_setzero_ps(), one = set(1.0f), half = set(0.5f);
    acc.den = zero;
    acc.worst = zero;
    for (int64_t c = 0; c < C; ++c) acc.num[c] = zero;
    if (ok_bits == 0) return;  // no lane to warp (e.g. sky): no taps
    if (BILINEAR) {
        const __m256 fxs = sub(px.u, half), fys = sub(px.v, half);
        const __m256 x0 = _mm256_floor_ps(fxs), y0 = _mm256_floor_ps(fys);
        const __m256 fx = sub(fxs, x0), fy = sub(fys, y0);
        const __m256 x1 = add(x0, one), y1 = add(y0, one);
        const __m256 gx = sub(one, fx), gy = sub(one, fy);
        const __m256 ys[2] = {y0, y1}, wy[2] = {gy, fy};
        // Rectified stereo (epipolar lines = rows) gives fy = 0: the y1 taps then have weight 0 in every lane and
        // would add exactly +0 to den and num (and code 0), so skipping them changes no bit.
        const int rows = _mm256_movemask_ps(gt(fy, zero)) != 0 ? 2 : 1;
        for (int r = 0; r < rows; ++r) {  // taps in torch's order: (x0, y0), (x1, y0), (x0, y1), (x1, y1)
            if (s.Ws >= 2) {
                gather_pairs<NC, L>(s, k, x0, ys[r], ga, gb);
            } else {
                gather_taps<NC, L>(s, k, x0, ys[r], ga);
                gather_taps<NC, L>(s, k, x1, ys[r], gb);
            }
            tap<NC, CODES>(s, k, ga, x0, ys[r], mul(gx, wy[r]), px, acc.den, acc.num, acc.worst);
            tap<NC, CODES>(s, k, gb, x1, ys[r], mul(fx, wy[r]), px, acc.den, acc.num, acc.worst);
        }
    } else {
        const __m256 xi = _mm256_floor_ps(px.u), yi = _mm256_floor_ps(px.v);
        gather_taps<NC, L>(s, k, xi, yi, ga);
        tap<NC, CODES>(s, k, ga, xi, yi, one, px, acc.den, acc.num, acc.worst);
    }
}

// Writes the results of 8 pixels at position x of the row outputs.
template <int NC>
SR_AVX2 SR_INLINE void store8(const Source &s, const RowOut &o, int64_t x, const Pixels8 &px, const Sums8<NC> &acc,
                              __m256 has_w) {
    const int64_t C = NC > 0 ? NC : s.C;
    const __m256 safe_den = sel(has_w, acc.den, set(1.0f));
    for (int64_t c = 0; c < C; ++c) st8(o.num[c], x, band(_mm256_div_ps(acc.num[c], safe_den), has_w));
    _mm256_storeu_ps(o.den + x, acc.den);
    __m256 reason = sel(px.front, acc.worst, set(BEHIND_CAMERA));
    reason = sel(px.dst_ok, reason, set(NO_SURFACE_DST));
    reason = _mm256_andnot_ps(has_w, reason);
    alignas(32) int32_t r[8];
    _mm256_store_si256((__m256i *)r, _mm256_cvttps_epi32(reason));
    const int vm = _mm256_movemask_ps(has_w);
    for (int l = 0; l < 8; ++l) {
        o.reason[x + l] = (uint8_t)r[l];
        o.valid[x + l] = (uint8_t)((vm >> l) & 1);
    }
}

// Warps pixels [0, W - W % 8) of row y; returns the first pixel not done.
template <int NC, bool BILINEAR, class L>
SR_AVX2 int64_t warp_row(const Source &s, const Dest &d, const Camera &cam, const Tests &th, int64_t y,
                         const RowOut &o) {
    Warp8 w;
    Consts k;
    broadcast_camera(s, cam, th, w, k);
    Taps<NC> ga, gb;
    Sums8<NC> acc;
    Pixels8 px;
    const __m256 vc = set((float)y + 0.5f), half = set(0.5f), zero = _mm256_setzero_ps();
    const __m256i iota = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    int64_t x = 0;
    for (; x + 8 <= d.W; x += 8) {
        const __m256 uc = add(_mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32((int32_t)x), iota)), half);
        project8<L>(d, w, y * d.W + x, uc, vc, px);
        const int ok_bits = _mm256_movemask_ps(px.pixel_ok);
        taps8<NC, BILINEAR, false, L>(s, k, px, ok_bits, ga, gb, acc);
        const __m256 has_w = gt(acc.den, zero);
        // A pixel that was warped but kept nothing reports the code of its most nearly accepted tap: only for such
        // groups (a few %) are the taps run again with codes (same arithmetic, so den and num come out the same).
        if (ok_bits & ~_mm256_movemask_ps(has_w)) taps8<NC, BILINEAR, true, L>(s, k, px, ok_bits, ga, gb, acc);
        store8<NC>(s, o, x, px, acc, has_w);
    }
    return x;
}

// TemporalSink::finish for x in [0, W - W % 8): the same operations as the scalar loop, 8 pixels at a time.
SR_AVX2 int64_t blend_row(const float *n, const uint8_t *valid, const float *const *hist, const Plane *cur,
                          const OutPlane *out, float *len, float alpha, float max_history, bool warmup,
                          bool round_history, int64_t Cc, int64_t W) {
    const __m256 zero = _mm256_setzero_ps(), one = set(1.0f), va = set(alpha), cap = set(max_history);
    int64_t x = 0;
    for (; x + 8 <= W; x += 8) {
        const __m256i b = _mm256_cvtepu8_epi32(_mm_loadl_epi64(reinterpret_cast<const __m128i *>(valid + x)));
        const __m256 v = _mm256_castsi256_ps(_mm256_cmpgt_epi32(b, _mm256_setzero_si256()));
        // n > 0 ? n : 0 (negative or NaN: no history): _mm256_max_ps returns its second operand unless first > second
        const __m256 nx = _mm256_max_ps(_mm256_loadu_ps(n + x), zero);
        // std::max(p, q) is (p < q) ? q : p, i.e. _mm256_max_ps(q, p) (which returns its second operand on ties)
        const __m256 a = warmup ? _mm256_max_ps(va, _mm256_div_ps(one, add(nx, one))) : va;
        // round_history: round half to even (the default rounding mode), as torch.round and ONNX Round
        const __m256 nr = round_history ? _mm256_round_ps(nx, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC) : nx;
        _mm256_storeu_ps(len + x, sel(v, _mm256_min_ps(add(nr, one), cap), one));
        const __m256 ga = sub(one, a);
        for (int64_t c = 0; c < Cc; ++c) {
            const __m256 h = _mm256_loadu_ps(hist[c] + x), cx = ld8(cur[c], x);
            st8(out[c], x, sel(v, add(mul(ga, h), mul(a, cx)), cx));
        }
    }
    return x;
}
}  // namespace v8

bool use_avx2() {  // and F16C (a float16 plane may come)
    static const bool ok = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("f16c");
    return ok;
}
#endif

template <int NC, bool BILINEAR, class L>
void warp_row(const Source &s, const Dest &d, const Camera &cam, const Tests &th, int64_t y, const RowOut &o,
              bool vector) {
    int64_t x = 0;
#ifdef SR_AVX2_PATH
    if (vector) x = v8::warp_row<NC, BILINEAR, L>(s, d, cam, th, y, o);
#endif
    for (; x < d.W; ++x) warp_pixel<NC, BILINEAR, L>(s, d, cam, th, x, y, o);
}

// ---- sinks: where a warped row goes ------------------------------------------------------------------------
// Stereo: the row outputs are the output arrays themselves (the confidence row goes to scratch when not wanted).
struct StereoSink {
    OutPlane values;  // (B, C, H, W)
    bool *valid;
    uint8_t *reason;
    float *conf;  // nullptr: not wanted
    int64_t C, H, W;
    bool needs_scratch() const { return conf == nullptr; }
    RowOut row(int64_t b, int64_t y, float *scratch) const {
        RowOut o;
        for (int64_t c = 0; c < C; ++c) o.num[c] = values + ((b * C + c) * H + y) * W;
        const int64_t i = (b * H + y) * W;
        o.den = conf ? conf + i : scratch;
        o.reason = reason + i;
        o.valid = reinterpret_cast<uint8_t *>(valid + i);  // bool is one byte holding 0 or 1
        return o;
    }
    void finish(int64_t, int64_t, const RowOut &) const {}
};

// Temporal: warp [history colour, history length] into scratch rows, then temporal_blend with a bool confidence.
struct TemporalSink {
    Plane current;   // (B, C-1, H, W)
    OutPlane color;  // (B, C-1, H, W)
    float *len;      // (B, 1, H, W)
    bool *valid;
    float alpha, max_history;
    bool warmup;
    bool round_history;  // store round_half_even(n) + 1 (BMFR's integer count) instead of n + 1
    bool footprint;      // n *= 0.5 + 0.5·min(max(den, 0), 1) before the blend (footprint quality)
    int64_t C, H, W;
    bool vector;  // AVX2 blend
    bool needs_scratch() const { return true; }
    RowOut row(int64_t b, int64_t y, float *scratch) const {  // scratch: (C + 2) * W floats
        RowOut o;
        for (int64_t c = 0; c < C; ++c) o.num[c] = OutPlane{scratch + c * W, false};
        o.den = scratch + C * W;
        o.reason = reinterpret_cast<uint8_t *>(scratch + (C + 1) * W);
        o.valid = reinterpret_cast<uint8_t *>(valid + (b * H + y) * W);
        return o;
    }
    void finish(int64_t b, int64_t y, const RowOut &o) const {
        // same operations as reproject.temporal_blend: n = n > 0 ? n : 0, a = max(1/(n + 1), alpha) (warmup) or
        // alpha, out = (1 - a)·hist + a·cur where valid else cur, n_out = min(n + 1, max_history) where valid else 1
        // (round_history: min(nearbyint(n) + 1, max_history), nearbyint rounding half to even).
        const int64_t Cc = C - 1, row = (b * H + y) * W;
        float *n = o.num[Cc].f32();  // a scratch row
        if (footprint) {
            // the same operations as reproject.functional._footprint_weighted: q = clamp(den, 0, 1),
            // n·(0.5 + 0.5·q), rounded after each operation (the scalar code is built for the baseline ISA: no FMA)
            for (int64_t x = 0; x < W; ++x) {
                const float dq = o.den[x] < 1.0f ? o.den[x] : 1.0f;
                const float q = dq > 0.0f ? dq : 0.0f;
                n[x] = n[x] * (0.5f + 0.5f * q);
            }
        }
        const uint8_t *v = o.valid;
        float *lo = len + row;
        const float *hist[kMaxStackChannels];
        Plane cur[kMaxStackChannels];
        OutPlane out[kMaxStackChannels];
        for (int64_t c = 0; c < Cc; ++c) {
            const int64_t off = ((b * Cc + c) * H + y) * W;
            hist[c] = o.num[c].f32();
            cur[c] = current + off;
            out[c] = color + off;
        }
        int64_t x0 = 0;
#ifdef SR_AVX2_PATH
        if (vector) x0 = v8::blend_row(n, v, hist, cur, out, lo, alpha, max_history, warmup, round_history, Cc, W);
#endif
        for (int64_t x = x0; x < W; ++x) {
            const float nx = n[x] > 0.0f ? n[x] : 0.0f;
            const float a = warmup ? std::max(1.0f / (nx + 1.0f), alpha) : alpha;
            const float nr = round_history ? std::nearbyint(nx) : nx;
            lo[x] = v[x] ? std::min(nr + 1.0f, max_history) : 1.0f;
            for (int64_t c = 0; c < Cc; ++c) {
                const float cx = cur[c][x];
                out[c].set(x, v[x] ? (1.0f - a) * hist[c][x] + a * cx : cx);
            }
        }
    }
};

struct Batch {  // pointers and strides shared by all rows
    std::vector<Plane> chan;  // B * C value planes
    Plane src_depth, src_normal, dst_depth, dst_normal;
    Plane motion, motion_world;  // (B, 2, H, W), (B, 3, H, W) when has_motion / has_world
    bool has_motion = false, has_world = false;
    const float *P, *kt, *M, *t, *Ki;
    const float *R = nullptr;  // (B, 9) source rotations, with has_world or the plane test
    int64_t B, C, Hs, Ws, H, W;
};

template <int NC, bool BILINEAR, class L, class Sink>
void run_rows(const Batch &bt, const Tests &th, const Sink &sink) {
    const int64_t rows = bt.B * bt.H, HWs = bt.Hs * bt.Ws, HW = bt.H * bt.W;
    bool vector = false;
#ifdef SR_AVX2_PATH
    // int32 gather indices; coordinates exact in float32
    vector = use_avx2() && HWs < (int64_t(1) << 31) && bt.Ws < kF32ExactInt && bt.Hs < kF32ExactInt &&
             bt.W < kF32ExactInt;
#endif
#ifdef STEREOREPRO_OPENMP
#pragma omp parallel
#endif
    {
        std::vector<float> scratch(sink.needs_scratch() ? (bt.C + 2) * bt.W : 0);
#ifdef STEREOREPRO_OPENMP
#pragma omp for schedule(dynamic, 4)
#endif
        for (int64_t r = 0; r < rows; ++r) {
            const int64_t b = r / bt.H, y = r % bt.H;
            Source s;
            s.C = bt.C;
            s.Hs = bt.Hs;
            s.Ws = bt.Ws;
            for (int64_t c = 0; c < bt.C; ++c) s.chan[c] = bt.chan[b * bt.C + c];
            s.depth = bt.src_depth + b * HWs;
            s.n0 = bt.src_normal + (b * 3 + 0) * HWs;
            s.n1 = bt.src_normal + (b * 3 + 1) * HWs;
            s.n2 = bt.src_normal + (b * 3 + 2) * HWs;
            Dest d;
            d.depth = bt.dst_depth + b * HW;
            d.n0 = bt.dst_normal + (b * 3 + 0) * HW;
            d.n1 = bt.dst_normal + (b * 3 + 1) * HW;
            d.n2 = bt.dst_normal + (b * 3 + 2) * HW;
            d.H = bt.H;
            d.W = bt.W;
            d.motion = bt.has_motion;
            d.world = bt.has_world;
            if (bt.has_motion) {
                d.mo0 = bt.motion + (b * 2 + 0) * HW;
                d.mo1 = bt.motion + (b * 2 + 1) * HW;
            }
            if (bt.has_world) {
                d.mw0 = bt.motion_world + (b * 3 + 0) * HW;
                d.mw1 = bt.motion_world + (b * 3 + 1) * HW;
                d.mw2 = bt.motion_world + (b * 3 + 2) * HW;
            }
            const Camera cam{bt.P + 9 * b, bt.kt + 3 * b, bt.M + 9 * b,
                             bt.t + 3 * b, bt.Ki + 9 * b, bt.R ? bt.R + 9 * b : nullptr};
            const RowOut o = sink.row(b, y, scratch.data());
            warp_row<NC, BILINEAR, L>(s, d, cam, th, y, o, vector);
            if (BILINEAR && th.cubic) cubic_row<NC, L>(s, d, cam, th, y, o);
            sink.finish(b, y, o);
        }
    }
}

template <class L, class Sink>
void dispatch_channels(const Batch &bt, const Tests &th, bool bilinear, const Sink &sink) {
    if (bt.C == 3) {
        bilinear ? run_rows<3, true, L>(bt, th, sink) : run_rows<3, false, L>(bt, th, sink);
    } else if (bt.C == 4) {
        bilinear ? run_rows<4, true, L>(bt, th, sink) : run_rows<4, false, L>(bt, th, sink);
    } else {
        bilinear ? run_rows<0, true, L>(bt, th, sink) : run_rows<0, false, L>(bt, th, sink);
    }
}

// The Kind of a group of planes.
template <class It>
int kind_of(It first, It last) {
    bool any_half = false, any_float = false;
    for (; first != last; ++first) (first->half ? any_half : any_float) = true;
    return any_half ? (any_float ? ANY : F16) : F32;
}

template <class Sink>
void dispatch(const Batch &bt, const Tests &th, bool bilinear, const Sink &sink) {
    nb::gil_scoped_release release;
    const Plane zs[2] = {bt.src_depth, bt.dst_depth}, ns[2] = {bt.src_normal, bt.dst_normal};
    const int values = kind_of(bt.chan.begin(), bt.chan.end()), depth = kind_of(zs, zs + 2),
              normals = kind_of(ns, ns + 2);
    // float32; float16 colour and normals with float32 depths (the engine layout); all float16; any other mix
    if (values == F32 && depth == F32 && normals == F32)
        dispatch_channels<Layout<F32, F32, F32>>(bt, th, bilinear, sink);
    else if (values == F16 && depth == F32 && normals == F16)
        dispatch_channels<Layout<F16, F32, F16>>(bt, th, bilinear, sink);
    else if (values == F16 && depth == F16 && normals == F16)
        dispatch_channels<Layout<F16, F16, F16>>(bt, th, bilinear, sink);
    else
        dispatch_channels<Layout<ANY, ANY, ANY>>(bt, th, bilinear, sink);
}

// Checks the geometry arrays shared by both kernels and fills bt (except chan and C).
void check_geometry(Batch &bt, const CA &src_depth, const CA &src_normal, const CF &P, const CF &kt, const CF &M,
                    const CF &t, const CF &Ks_inv, const CA &dst_depth, const CA &dst_normal) {
    expect_shape(src_depth, "src_depth", {bt.B, 1, -1, -1});
    bt.Hs = src_depth.shape(2);
    bt.Ws = src_depth.shape(3);
    expect_shape(src_normal, "src_normal", {bt.B, 3, bt.Hs, bt.Ws});
    expect_shape(P, "P", {bt.B, 9});
    expect_shape(kt, "kt", {bt.B, 3});
    expect_shape(M, "M", {bt.B, 9});
    expect_shape(t, "t", {bt.B, 3});
    expect_shape(Ks_inv, "Ks_inv", {bt.B, 9});
    expect_shape(dst_depth, "dst_depth", {bt.B, 1, -1, -1});
    bt.H = dst_depth.shape(2);
    bt.W = dst_depth.shape(3);
    expect_shape(dst_normal, "dst_normal", {bt.B, 3, bt.H, bt.W});
    bt.src_depth = plane_of(src_depth, "src_depth");
    bt.src_normal = plane_of(src_normal, "src_normal");
    bt.dst_depth = plane_of(dst_depth, "dst_depth");
    bt.dst_normal = plane_of(dst_normal, "dst_normal");
    bt.P = P.data();
    bt.kt = kt.data();
    bt.M = M.data();
    bt.t = t.data();
    bt.Ki = Ks_inv.data();
}

// Checks the optional motion arrays (of the destination view) and the source rotations, and fills bt's motion.
void check_motion(Batch &bt, const std::optional<CA> &motion, const std::optional<CA> &motion_world,
                  const std::optional<CF> &R) {
    if (!motion) {
        if (motion_world) throw std::invalid_argument("reproject: motion_world needs motion");
        return;
    }
    expect_shape(*motion, "motion", {bt.B, 2, bt.H, bt.W});
    bt.motion = plane_of(*motion, "motion");
    bt.has_motion = true;
    if (!motion_world) return;
    expect_shape(*motion_world, "motion_world", {bt.B, 3, bt.H, bt.W});
    if (!R) throw std::invalid_argument("reproject: motion_world needs R (the source rotations)");
    expect_shape(*R, "R", {bt.B, 9});
    bt.motion_world = plane_of(*motion_world, "motion_world");
    bt.R = R->data();
    bt.has_world = true;
}

// The plane test needs the source rotations R (B, 9), with or without motion.
void check_plane(Batch &bt, const std::optional<CF> &R, bool plane) {
    if (!plane) return;
    if (!R) throw std::invalid_argument("reproject: plane needs R (the source rotations)");
    expect_shape(*R, "R", {bt.B, 9});
    bt.R = R->data();
}

void reproject(CA src_values, CA src_depth, CA src_normal, CF P, CF kt, CF M, CF t, CF Ks_inv, CA dst_depth,
               CA dst_normal, float pos_thr2, float nrm_thr2, bool bilinear, OA out_values, OB out_valid,
               OU8 out_reason, std::optional<OF> out_confidence, std::optional<CA> motion,
               std::optional<CA> motion_world, std::optional<CF> R, bool cubic, bool plane) {
    if (src_values.ndim() != 4) throw std::invalid_argument("reproject: src_values must be 4-D (B, C, Hs, Ws)");
    Batch bt;
    bt.B = src_values.shape(0);
    bt.C = src_values.shape(1);
    if (bt.C < 1 || bt.C > kMaxStackChannels)
        throw std::invalid_argument("reproject: src_values must have 1.." + std::to_string(kMaxStackChannels) +
                                    " channels, got " + std::to_string(bt.C));
    check_geometry(bt, src_depth, src_normal, P, kt, M, t, Ks_inv, dst_depth, dst_normal);
    expect_shape(src_values, "src_values", {bt.B, bt.C, bt.Hs, bt.Ws});
    expect_shape(out_values, "out_values", {bt.B, bt.C, bt.H, bt.W});
    expect_shape(out_valid, "out_valid", {bt.B, 1, bt.H, bt.W});
    expect_shape(out_reason, "out_reason", {bt.B, 1, bt.H, bt.W});
    if (out_confidence) expect_shape(*out_confidence, "out_confidence", {bt.B, 1, bt.H, bt.W});
    check_motion(bt, motion, motion_world, R);
    check_plane(bt, R, plane);
    const int64_t HWs = bt.Hs * bt.Ws;
    bt.chan.resize(bt.B * bt.C);
    const Plane values = plane_of(src_values, "src_values");
    for (int64_t i = 0; i < bt.B * bt.C; ++i) bt.chan[i] = values + i * HWs;
    const StereoSink sink{plane_of(out_values, "out_values"), out_valid.data(), out_reason.data(),
                          out_confidence ? out_confidence->data() : nullptr, bt.C, bt.H, bt.W};
    dispatch(bt, Tests{pos_thr2, nrm_thr2, cubic, plane}, bilinear || cubic, sink);
}

void temporal_reproject(CA current, CA history_color, CA history_len, CA prev_depth, CA prev_normal, CF P, CF kt,
                        CF M, CF t, CF Ks_inv, CA depth, CA normal, float pos_thr2, float nrm_thr2, bool bilinear,
                        float alpha, bool warmup, float max_history, OA out_color, OF out_len, OB out_valid,
                        std::optional<CA> motion, std::optional<CA> motion_world, std::optional<CF> R,
                        bool round_history, bool cubic, bool footprint, bool plane) {
    if (history_color.ndim() != 4)
        throw std::invalid_argument("temporal_reproject: history_color must be 4-D (B, C, Hs, Ws)");
    Batch bt;
    bt.B = history_color.shape(0);
    const int64_t Cc = history_color.shape(1);
    bt.C = Cc + 1;
    if (Cc < 1 || bt.C > kMaxStackChannels)
        throw std::invalid_argument("temporal_reproject: history_color must have 1.." +
                                    std::to_string(kMaxStackChannels - 1) + " channels");
    check_geometry(bt, prev_depth, prev_normal, P, kt, M, t, Ks_inv, depth, normal);
    expect_shape(history_color, "history_color", {bt.B, Cc, bt.Hs, bt.Ws});
    expect_shape(history_len, "history_len", {bt.B, 1, bt.Hs, bt.Ws});
    expect_shape(current, "current", {bt.B, Cc, bt.H, bt.W});
    expect_shape(out_color, "out_color", {bt.B, Cc, bt.H, bt.W});
    expect_shape(out_len, "out_len", {bt.B, 1, bt.H, bt.W});
    expect_shape(out_valid, "out_valid", {bt.B, 1, bt.H, bt.W});
    check_motion(bt, motion, motion_world, R);
    check_plane(bt, R, plane);
    const int64_t HWs = bt.Hs * bt.Ws;
    bt.chan.resize(bt.B * bt.C);
    const Plane hc = plane_of(history_color, "history_color"), hl = plane_of(history_len, "history_len");
    for (int64_t b = 0; b < bt.B; ++b) {
        for (int64_t c = 0; c < Cc; ++c) bt.chan[b * bt.C + c] = hc + (b * Cc + c) * HWs;
        bt.chan[b * bt.C + Cc] = hl + b * HWs;
    }
    bool vector = false;
#ifdef SR_AVX2_PATH
    vector = use_avx2();
#endif
    const TemporalSink sink{plane_of(current, "current"), plane_of(out_color, "out_color"), out_len.data(),
                            out_valid.data(), alpha, max_history, warmup, round_history, footprint,
                            bt.C, bt.H, bt.W, vector};
    dispatch(bt, Tests{pos_thr2, nrm_thr2, cubic, plane}, bilinear || cubic, sink);
}

// Fast-history clamp (NVIDIA NRD's RELAX), the native twin of stereorepro.reproject.clamp._clamp_checked, with the
// same float32 operations in the same order (so the same bytes): per (b, c) plane the window sums of the finite
// fast values x0 (0 where not finite), of x0 * x0 and of the finite count, separable (rows, then columns; each
// sum starts at the window's first term and adds the following ones in order, 0 for a term outside the frame,
// as torch's sum of shifted slices of a zero-padded copy); then mean = s1 / n, var = s2 / n - mean * mean,
// std = var > 0 ? sqrt(var) : 0, half = sigma * std, out = min(max(c, mean - half), mean + half) (NaN-propagating
// like torch.maximum / minimum), and out = c where the window holds no finite value.
SR_INLINE float nan_max(float a, float b) { return a != a ? a : b != b ? b : a > b ? a : b; }
SR_INLINE float nan_min(float a, float b) { return a != a ? a : b != b ? b : a < b ? a : b; }

// One row of a float32 or float16 plane as float32 (float16 widened exactly).
SR_INLINE void load_row(const Plane &p, int64_t off, int64_t n, float *dst) {
    if (p.half)
        for (int64_t i = 0; i < n; ++i) dst[i] = load<ANY>(p, off + i);
    else
        std::memcpy(dst, p.f32() + off, n * sizeof(float));
}

void fast_history_clamp(CA color, CA fast, float sigma, int64_t radius, OA out) {
    if (color.ndim() != 4) throw std::invalid_argument("fast_history_clamp: color must be 4-D (B, C, H, W)");
    const int64_t B = color.shape(0), C = color.shape(1), H = color.shape(2), W = color.shape(3);
    expect_shape(fast, "fast", {B, C, H, W});
    expect_shape(out, "out", {B, C, H, W});
    if (radius < 0) throw std::invalid_argument("fast_history_clamp: radius must be >= 0");
    const Plane cp = plane_of(color, "color"), fp = plane_of(fast, "fast");
    const OutPlane op = plane_of(out, "out");
    nb::gil_scoped_release release;
    const int64_t HW = H * W, r = radius, taps = 2 * radius + 1, Wp = W + 2 * radius;
    std::vector<float> h1(HW), h2(HW), hn(HW), zero(W, 0.0f);  // the row sums of one plane; a zero row
    for (int64_t p = 0; p < B * C; ++p) {
        const Plane f = fp + p * HW, c = cp + p * HW;
        const OutPlane o = op + p * HW;
#ifdef STEREOREPRO_OPENMP
#pragma omp parallel
#endif
        {
            std::vector<float> row(W), b1(Wp, 0.0f), b2(Wp, 0.0f), bn(Wp, 0.0f);  // zero-padded by r
#ifdef STEREOREPRO_OPENMP
#pragma omp for schedule(static)
#endif
            for (int64_t y = 0; y < H; ++y) {
                load_row(f, y * W, W, row.data());
#pragma omp simd
                for (int64_t x = 0; x < W; ++x) {
                    const float v = row[x];
                    const bool ok = finitef(v);
                    b1[x + r] = ok ? v : 0.0f;
                    b2[x + r] = ok ? v * v : 0.0f;
                    bn[x + r] = ok ? 1.0f : 0.0f;
                }
                float *s1 = h1.data() + y * W, *s2 = h2.data() + y * W, *sn = hn.data() + y * W;
#pragma omp simd
                for (int64_t x = 0; x < W; ++x) s1[x] = b1[x], s2[x] = b2[x], sn[x] = bn[x];
                for (int64_t i = 1; i < taps; ++i)
#pragma omp simd
                    for (int64_t x = 0; x < W; ++x)
                        s1[x] = s1[x] + b1[x + i], s2[x] = s2[x] + b2[x + i], sn[x] = sn[x] + bn[x + i];
            }
        }
#ifdef STEREOREPRO_OPENMP
#pragma omp parallel
#endif
        {
            std::vector<float> v1(W), v2(W), vn(W), cur(W), res(W);
#ifdef STEREOREPRO_OPENMP
#pragma omp for schedule(static)
#endif
            for (int64_t y = 0; y < H; ++y) {
                for (int64_t i = 0; i < taps; ++i) {  // rows y - r .. y + r in order
                    const int64_t k = y - r + i;
                    const bool in = k >= 0 && k < H;  // outside: a zero row, added like torch's padding
                    const float *a1 = in ? h1.data() + k * W : zero.data(), *a2 = in ? h2.data() + k * W : zero.data(),
                                *an = in ? hn.data() + k * W : zero.data();
                    if (i == 0) {
#pragma omp simd
                        for (int64_t x = 0; x < W; ++x) v1[x] = a1[x], v2[x] = a2[x], vn[x] = an[x];
                    } else {
#pragma omp simd
                        for (int64_t x = 0; x < W; ++x)
                            v1[x] = v1[x] + a1[x], v2[x] = v2[x] + a2[x], vn[x] = vn[x] + an[x];
                    }
                }
                load_row(c, y * W, W, cur.data());
                // three loops: the square roots (scalar: errno-setting sqrt) apart, so the other two vectorise
#pragma omp simd
                for (int64_t x = 0; x < W; ++x) {
                    const float safe = vn[x] > 0.0f ? vn[x] : 1.0f, mean = v1[x] / safe;
                    v1[x] = mean;
                    v2[x] = v2[x] / safe - mean * mean;  // the variance
                }
                for (int64_t x = 0; x < W; ++x) v2[x] = v2[x] > 0.0f ? std::sqrt(v2[x]) : 0.0f;
#pragma omp simd
                for (int64_t x = 0; x < W; ++x) {
                    const float mean = v1[x], half = sigma * v2[x], cv = cur[x];
                    res[x] = vn[x] > 0.0f ? nan_min(nan_max(cv, mean - half), mean + half) : cv;
                }
                if (o.half)
                    for (int64_t x = 0; x < W; ++x) o.f16()[y * W + x] = float_to_half(res[x]);
                else
                    std::memcpy(o.f32() + y * W, res.data(), W * sizeof(float));
            }
        }
    }
}

}  // namespace

void bind_reproject(nb::module_ &m) {
    // The mirrored constants, for the test that they equal stereorepro.reproject._constants.MIRRORED_IN_CORE.
    nb::dict constants;
    constants["COORD_MARGIN"] = nb::cast(kCoordMargin);
    constants["F32_EXACT_INT"] = nb::cast(kF32ExactInt);
    constants["MAX_CHANNELS"] = nb::cast(kMaxStackChannels);
    constants["PLANE_BASE"] = nb::cast(kPlaneBase);
    constants["PLANE_SLOPE"] = nb::cast(kPlaneSlope);
    constants["PLANE_MIN_NORMAL2"] = nb::cast(kPlaneMinNormal2);
    const std::pair<const char *, uint8_t> reasons[] = {
        {"REASON_KEPT", KEPT},
        {"REASON_NO_SURFACE_DST", NO_SURFACE_DST},
        {"REASON_BEHIND_CAMERA", BEHIND_CAMERA},
        {"REASON_OUT_OF_FRAME", OUT_OF_FRAME},
        {"REASON_NO_SURFACE_SRC", NO_SURFACE_SRC},
        {"REASON_POSITION", POSITION},
        {"REASON_NORMAL", NORMAL},
        {"REASON_NONFINITE", NONFINITE}};
    for (const auto &[name, code] : reasons) constants[name] = nb::cast(int(code));
    m.attr("reproject_constants") = constants;
    m.def("reproject", &reproject, nb::arg("src_values").noconvert(), nb::arg("src_depth").noconvert(),
          nb::arg("src_normal").noconvert(), nb::arg("P").noconvert(), nb::arg("kt").noconvert(),
          nb::arg("M").noconvert(), nb::arg("t").noconvert(), nb::arg("Ks_inv").noconvert(),
          nb::arg("dst_depth").noconvert(), nb::arg("dst_normal").noconvert(), nb::arg("pos_thr2"),
          nb::arg("nrm_thr2"), nb::arg("bilinear"), nb::arg("out_values").noconvert(),
          nb::arg("out_valid").noconvert(), nb::arg("out_reason").noconvert(),
          nb::arg("out_confidence").noconvert().none(), nb::arg("motion").noconvert().none() = nb::none(),
          nb::arg("motion_world").noconvert().none() = nb::none(), nb::arg("R").noconvert().none() = nb::none(),
          nb::arg("cubic") = false, nb::arg("plane") = false,
          "Fused hard backward reprojection (NCHW, C-contiguous CPU arrays; no copies are made). Image arrays "
          "(values, depths, normals, out_values) are float32 or float16, each on its own; compute is float32.\n"
          "Camera arrays P, M, Ks_inv are (B, 9) row-major and kt, t are (B, 3), composed by "
          "stereorepro.camera.compose_warp. pos_thr2 / nrm_thr2 are the float32 squared thresholds.\n"
          "Writes out_values (B, C, H, W), out_valid (B, 1, H, W) bool, out_reason (B, 1, H, W) uint8 and "
          "out_confidence (B, 1, H, W) in place; out_confidence may be None (not computed).\n"
          "motion (B, 2, H, W) and motion_world (B, 3, H, W) (float32 or float16, optional) are the destination's "
          "motion vectors: taps at pixel + motion, the position test against q + R * motion_world, R (B, 9) the "
          "source camera's rotation (row-major); non-finite motion: OUT_OF_FRAME.\n"
          "cubic: sampling=\"catmull_rom\" (the bilinear pass, then the 4x4 Catmull-Rom sum where all 16 footprint "
          "taps pass, clamped at 0).\n"
          "plane: the plane test (position_test=\"plane\"): |n.(P_src - q)|^2 <= pos_thr2 * scale^2, scale = z / "
          "(0.05 + 0.95 |n.v|), n the destination normal rotated by R (B, 9), needed then.");
    m.def("fast_history_clamp", &fast_history_clamp, nb::arg("color").noconvert(), nb::arg("fast").noconvert(),
          nb::arg("sigma"), nb::arg("radius"), nb::arg("out").noconvert(),
          "Fast-history clamp (NRD RELAX), the twin of stereorepro.reproject.fast_history_clamp: out = color clamped "
          "per channel to mean +- sigma * std of the finite in-frame values of fast in the (2 radius + 1)^2 window "
          "(color where the window has none). color, fast (B, C, H, W) and out float32 or float16, each on its own; "
          "compute is float32, in torch's order (same bytes).");
    m.def("temporal_reproject", &temporal_reproject, nb::arg("current").noconvert(),
          nb::arg("history_color").noconvert(), nb::arg("history_len").noconvert(),
          nb::arg("prev_depth").noconvert(), nb::arg("prev_normal").noconvert(), nb::arg("P").noconvert(),
          nb::arg("kt").noconvert(), nb::arg("M").noconvert(), nb::arg("t").noconvert(),
          nb::arg("Ks_inv").noconvert(), nb::arg("depth").noconvert(), nb::arg("normal").noconvert(),
          nb::arg("pos_thr2"), nb::arg("nrm_thr2"), nb::arg("bilinear"), nb::arg("alpha"), nb::arg("warmup"),
          nb::arg("max_history"), nb::arg("out_color").noconvert(), nb::arg("out_len").noconvert(),
          nb::arg("out_valid").noconvert(), nb::arg("motion").noconvert().none() = nb::none(),
          nb::arg("motion_world").noconvert().none() = nb::none(), nb::arg("R").noconvert().none() = nb::none(),
          nb::arg("round_history") = false, nb::arg("cubic") = false, nb::arg("footprint") = false,
          nb::arg("plane") = false,
          "Fused temporal reprojection: warps [history_color, history_len] like `reproject` and blends with "
          "`current` in the same pass (a = max(1/(n+1), alpha) with warmup, else alpha). Where the history is "
          "kept out_len = min(n + 1, max_history), or with round_history min(round_half_even(n) + 1, "
          "max_history) (BMFR's integer count); with footprint n is first multiplied by 0.5 + 0.5 * clamp(den, "
          "0, 1), den the accepted bilinear weight (footprint quality). Writes out_color "
          "(float32 or float16), out_len (float32) and out_valid in place; image inputs float32 or float16. "
          "motion, motion_world, R, cubic, plane: as in `reproject` (the motion of this frame to the previous one).");
}
