// Wavefront path-tracer stages other than intersection: the native twin of the numpy reference in
// stereorepro/render/tracer.py (with bsdf.py, lights.py, rng.py). Embree intersection stays in Python (embreex);
// these kernels run between its queries on structure-of-arrays batches (float32 / int32 / uint64, C-contiguous).
// They are the native stages of tracer.STAGES (tracer._NativeStages calls them):
//
//   tracer_generate          generate: keys + primary rays (jittered pixel position, camera matrix, unit
//                            direction);
//   TracerShader.shade1      shade_x1, after the primary query: surface, directly seen emission, NEE at x1
//                            (shadow ray + MIS-weighted value), BSDF sample of the bounce (compacted bounce rays);
//   TracerShader.shade2      shade_x2, after the bounce query: surface at x2, MIS-weighted emission of x2, NEE at
//                            x2 (shadow rays appended after those of x1, so one occlusion query tests both sets);
//   TracerShader.accumulate  accumulate, after the occlusion query: visible NEE values, x2's and x1's clamps, the
//                            sample.
//
// Parity with numpy: every float32 operation follows the numpy code in the same order (a*b + c*d + e*f is
// (a*b + c*d) + e*f, divisions stay divisions), without FMA contraction. The azimuth (cos, sin) of a sampled
// direction is a float32 polynomial evaluated the same way on both sides (unit_circle = bsdf.unit_circle); pow
// (glossy lobes) is a float64 libm call cast to float32 in both paths (bsdf.py does the same in numpy float64),
// because numpy's float32 SIMD transcendentals differ from libm in the last bit. Light selection compares float64
// CDF values as np.searchsorted(side="right") does. Result: bit-identical radiance
// (tests/render/test_render_native.py).
//
// Layout inside a kernel: paths are processed in blocks of kBlock lanes held as a structure of arrays (Lanes,
// NeeBlock). Each step of next-event estimation and of Lambertian BSDF sampling is a loop over the block: the
// integer work (hashing, light selection, table lookups) stays scalar, the float work is `#pragma omp simd` loops
// of selects instead of branches, which the compiler vectorises (SSE2 at the x86-64 baseline; -fno-trapping-math
// and -fno-math-errno in CMakeLists.txt let it: values are unchanged, vector sqrt/div/mul/add round exactly as
// scalar ones). Compaction of shadow and bounce rays is branchless (write, then advance the count by the keep
// flag) and keeps path order.
//
// Threading: none inside. The Python tracer already runs one worker thread per pixel range and each worker runs
// its own embreex queries and these kernels (both release the GIL), so a second (OpenMP) level would only
// oversubscribe the cores and serialise the embreex calls behind a shading barrier.
#if defined(__clang__)
#pragma clang fp contract(off)
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/tuple.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <string>
#include <tuple>
#include <vector>

#include "rng_tracer.h"

namespace nb = nanobind;

namespace {

template <class T>
using In = nb::ndarray<const T, nb::c_contig, nb::device::cpu>;
template <class T>
using Out = nb::ndarray<T, nb::c_contig, nb::device::cpu>;

constexpr float kInvPi = static_cast<float>(1.0 / 3.14159265358979323846);     // np.float32(1 / pi)
constexpr float kTwoPi = static_cast<float>(2.0 * 3.14159265358979323846);     // np.float32(2 pi)
constexpr float kInvTwoPi = 1.0f / kTwoPi;                                      // np.float32(1) / _TWO_PI
constexpr float kInf = std::numeric_limits<float>::infinity();

enum Dim : uint64_t { JX = 0, JY = 1, L1 = 2, L1U = 3, L1V = 4, LOBE = 5, BU = 6, BV = 7, L2 = 8, L2U = 9, L2V = 10 };

// np.maximum(x, 0) (NaN propagates, -0 gives +0) and np.maximum(x, lo) for lo > 0.
// (both tests evaluated first: without a branch, loops using them vectorise)
inline float maxlo(float x, float lo) {
    const bool above = x > lo, nan = x != x;
    return (above || nan) ? x : lo;
}
inline float max0(float x) { return maxlo(x, 0.0f); }
// rows.max(axis=1) of a 3-vector: NaN if any channel is NaN.
inline float max3(const float *v) {
    float m = v[0];
    for (int c = 1; c < 3; ++c)
        if (v[c] > m || v[c] != v[c]) m = (m != m) ? m : v[c];
    return m;
}
// rows.max(axis=1) > 0 for a 3-vector (NaN if any channel is NaN, so False then): some channel positive and none
// NaN, without branches (the order of the channels is a coin toss).
inline bool max3_positive(float x, float y, float z) {
    const bool p0 = x > 0.0f, p1 = y > 0.0f, p2 = z > 0.0f;
    const bool n0 = x == x, n1 = y == y, n2 = z == z;
    return (p0 || p1 || p2) && n0 && n1 && n2;
}
inline float dot3(const float *a, const float *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
// bsdf.unit_circle: (cos 2 pi u, sin 2 pi u) from a float32 polynomial, operation by operation as numpy does it.
inline void unit_circle(float u, float &cos_out, float &sin_out) {
    constexpr float kHalfPi = static_cast<float>(3.14159265358979323846 / 2.0);
    constexpr float s1 = static_cast<float>(-1.0 / 6.0), s2 = static_cast<float>(1.0 / 120.0),
                    s3 = static_cast<float>(-1.0 / 5040.0), s4 = static_cast<float>(1.0 / 362880.0),
                    s5 = static_cast<float>(-1.0 / 39916800.0);
    constexpr float c1 = static_cast<float>(-1.0 / 2.0), c2 = static_cast<float>(1.0 / 24.0),
                    c3 = static_cast<float>(-1.0 / 720.0), c4 = static_cast<float>(1.0 / 40320.0),
                    c5 = static_cast<float>(-1.0 / 3628800.0), c6 = static_cast<float>(1.0 / 479001600.0);
    const float u4 = u * 4.0f;
    const int iq4 = static_cast<int>(u4);  // u4 in [0, 4): truncation is np.floor (and vectorises without SSE4.1)
    const float q = static_cast<float>(iq4);
    const float a = (u4 - q) * kHalfPi;
    const float a2 = a * a;
    const float s = a * (1.0f + a2 * (s1 + a2 * (s2 + a2 * (s3 + a2 * (s4 + a2 * s5)))));
    const float c = 1.0f + a2 * (c1 + a2 * (c2 + a2 * (c3 + a2 * (c4 + a2 * (c5 + a2 * c6)))));
    // quadrant rotation by selects (no branch, no table: vectorises); q is 0..3 for u in [0, 1)
    const int iq = iq4 & 3;
    const bool q1 = iq == 1, q2 = iq == 2, q3 = iq == 3;
    cos_out = q1 ? -s : (q2 ? -c : (q3 ? s : c));
    sin_out = q1 ? c : (q2 ? -s : (q3 ? -c : s));
}
inline float fpow(float x, float e) { return static_cast<float>(std::pow(static_cast<double>(x), static_cast<double>(e))); }

// bsdf.to_world (with bsdf.onb, Duff et al. 2017), on scalars (no local arrays: vectorises in omp simd loops).
inline void to_world(float x, float y, float z, float lx, float ly, float lz, float &ox, float &oy, float &oz) {
    const bool up = z >= 0.0f;
    const float s = up ? 1.0f : -1.0f;
    const float a = -1.0f / (s + z);
    const float b = x * y * a;
    ox = (1.0f + s * x * x * a) * lx + b * ly + x * lz;
    oy = (s * b) * lx + (s + y * y * a) * ly + y * lz;
    oz = (-s * x) * lx + (-y) * ly + z * lz;
}
inline void to_world(const float *n, float lx, float ly, float lz, float *out) {
    to_world(n[0], n[1], n[2], lx, ly, lz, out[0], out[1], out[2]);
}

inline void reflect(const float *n, const float *wo, float *r) {
    const float k = 2.0f * dot3(n, wo);
    for (int c = 0; c < 3; ++c) r[c] = k * n[c] - wo[c];
}

template <class A>
void check_rows(const A &a, const char *name, int64_t rows, int64_t cols) {
    const bool ok = (cols == 0) ? (a.ndim() == 1 && (int64_t)a.shape(0) >= rows)
                                : (a.ndim() == 2 && (int64_t)a.shape(0) >= rows && (int64_t)a.shape(1) == cols);
    if (!ok)
        throw std::invalid_argument(std::string("tracer kernels: ") + name + " must have shape (" +
                                    std::to_string(rows) + (cols ? ", " + std::to_string(cols) : std::string(",")) +
                                    ") or more rows");
}

constexpr int kBlock = 16;  // shading points processed side by side

// Up to kBlock shading points, as a structure of arrays (so that per-lane steps vectorise): position, normal
// (facing wo), direction to the previous vertex, material, path key and path index.
struct Lanes {
    float P[3][kBlock], n[3][kBlock], wo[3][kBlock];
    int32_t mat[kBlock];
    uint64_t key[kBlock];
    int64_t path[kBlock];

    void set(int k, const float *P_, const float *n_, const float *wo_, int32_t mat_, uint64_t key_, int64_t path_) {
        for (int c = 0; c < 3; ++c) {
            P[c][k] = P_[c];
            n[c][k] = n_[c];
            wo[c][k] = wo_[c];
        }
        mat[k] = mat_;
        key[k] = key_;
        path[k] = path_;
    }
    void get(int k, float *P_, float *n_, float *wo_) const {
        for (int c = 0; c < 3; ++c) {
            P_[c] = P[c][k];
            n_[c] = n[c][k];
            wo_[c] = wo[c][k];
        }
    }
};

// Next-event estimation of a block of lanes: shadow ray (origin, direction, tmax), its value if unoccluded, and
// whether the ray is needed at all.
struct NeeBlock {
    float o[3][kBlock], wi[3][kBlock], tmax[kBlock], val[3][kBlock];
    int32_t ok[kBlock];
};

// One light sample per lane of a block, between the steps of nee_block: random numbers, the chosen light, the
// point on it (normal, emission, area pdf factor), distance, incident radiance, light and BSDF pdfs, BSDF value.
struct LightLanes {
    float u1[kBlock], u2[kBlock];
    int32_t sel[kBlock];
    float target[3][kBlock], ln[3][kBlock], le[3][kBlock], lpdf[kBlock];
    float d2[kBlock], dist[kBlock], li[3][kBlock], pdf_l[kBlock];
    float f[3][kBlock], cos_i[kBlock], pdf_b[kBlock];
};

struct ShadowBuf {  // compacted shadow-ray batch (both sets share it)
    float *o, *d, *t, *val;
    int32_t *path;
    int64_t cap;
};

class TracerShader {
public:
    TracerShader(In<float> face_normal, In<int32_t> face_material, In<float> kd, In<float> ks, In<float> exponent,
                 In<float> p_spec, In<float> emission, In<bool> mat_emissive, float eps, bool glossy,
                 bool lights_empty, In<double> cdf, In<double> prob, In<float> table, int64_t num_area,
                 In<float> point_pos, In<float> point_int, In<float> pdf_area_face)
        : face_normal_(face_normal), face_material_(face_material), kd_(kd), ks_(ks), exponent_(exponent),
          p_spec_(p_spec), emission_(emission), mat_emissive_(mat_emissive), cdf_(cdf), prob_(prob), table_(table),
          point_pos_(point_pos), point_int_(point_int), pdf_area_face_(pdf_area_face), eps_(eps), glossy_(glossy),
          lights_empty_(lights_empty), num_area_(num_area) {
        const int64_t F = face_normal.shape(0), M = kd.shape(0), K = cdf.shape(0);
        check_rows(face_normal, "face_normal", F, 3);
        check_rows(face_material, "face_material", F, 0);
        check_rows(pdf_area_face, "pdf_area_face", F, 0);
        check_rows(kd, "kd", M, 3);
        check_rows(emission, "emission", M, 3);
        check_rows(mat_emissive, "mat_emissive", M, 0);
        if (glossy) {
            check_rows(ks, "ks", M, 3);
            check_rows(exponent, "exponent", M, 0);
            check_rows(p_spec, "p_spec", M, 0);
        }
        check_rows(prob, "prob", K, 0);
        if (num_area < 0 || num_area > K) throw std::invalid_argument("TracerShader: num_area out of range");
        check_rows(table, "table", num_area, 16);
        check_rows(point_pos, "point_pos", K - num_area, 3);
        check_rows(point_int, "point_int", K - num_area, 3);
        if (!lights_empty && K == 0) throw std::invalid_argument("TracerShader: lights without a CDF");
        for (int64_t f = 0; f < F; ++f)
            if (face_material.data()[f] < 0 || face_material.data()[f] >= M)
                throw std::invalid_argument("TracerShader: face_material out of range");
    }

    // ---- stage shade_x1: after intersect_primary -----------------------------------------------------------
    std::tuple<int64_t, int64_t> shade1(In<uint64_t> keys, In<float> d, In<float> t, In<int32_t> prim,
                                        In<float> center, Out<float> L, Out<float> thr, Out<float> pdfb,
                                        Out<float> sh_o, Out<float> sh_d, Out<float> sh_t, Out<float> sh_val,
                                        Out<int32_t> sh_path, Out<float> b_o, Out<float> b_d, Out<int32_t> b_path) {
        const int64_t N = keys.shape(0);
        check_rows(d, "d", N, 3); check_rows(t, "t", N, 0); check_rows(prim, "prim", N, 0);
        check_rows(center, "center", 3, 0);
        check_rows(L, "L", N, 3); check_rows(thr, "thr", N, 3); check_rows(pdfb, "pdfb", N, 0);
        check_rows(b_o, "b_o", N, 3); check_rows(b_d, "b_d", N, 3); check_rows(b_path, "b_path", N, 0);
        ShadowBuf sb = shadow_buf(sh_o, sh_d, sh_t, sh_val, sh_path);
        if (sb.cap < N) throw std::invalid_argument("shade1: shadow buffers need >= N rows");
        check_prims(prim.data(), N);
        int64_t ns = 0, nbounce = 0;
        {
            nb::gil_scoped_release release;
            const uint64_t *K = keys.data();
            const float *D = d.data(), *T = t.data(), *C = center.data();
            const int32_t *Pr = prim.data();
            float *Lo = L.data(), *Th = thr.data(), *Pb = pdfb.data(), *Bo = b_o.data(), *Bd = b_d.data();
            int32_t *Bp = b_path.data();
            Lanes lane;
            NeeBlock res;
            for (int64_t i0 = 0; i0 < N; i0 += kBlock) {
                const int64_t i1 = std::min<int64_t>(N, i0 + kBlock);
                int m = 0;
                for (int64_t i = i0; i < i1; ++i) {  // surface and directly seen emission
                    float *li = Lo + 3 * i, *th = Th + 3 * i;
                    li[0] = li[1] = li[2] = 0.0f;
                    th[0] = th[1] = th[2] = 0.0f;
                    Pb[i] = 0.0f;
                    if (Pr[i] < 0) continue;
                    const float *di = D + 3 * i;
                    float P[3], n[3], wo[3];
                    for (int c = 0; c < 3; ++c) P[c] = C[c] + T[i] * di[c];
                    const int mat = surface(Pr[i], di, n);
                    for (int c = 0; c < 3; ++c) wo[c] = -di[c];
                    lane.set(m++, P, n, wo, mat, K[i], i);
                    if (mat_emissive_.data()[mat]) {
                        const float *e = emission_.data() + 3 * mat;
                        for (int c = 0; c < 3; ++c) li[c] = 0.0f + e[c];
                    }
                }
                if (!lights_empty_) {  // NEE at x1, shadow rays in path order
                    nee_block(m, lane, L1, L1U, L1V, true, res);
                    for (int k = 0; k < m; ++k) {
                        push_shadow(sb, ns, res, k, (int32_t)lane.path[k]);  // branchless compaction
                        ns += res.ok[k];
                    }
                }
                float wi[3][kBlock], weight[3][kBlock], pdf[kBlock];
                bsdf_sample_block(m, lane, wi, weight, pdf);  // BSDF sample of the bounce
                for (int k = 0; k < m; ++k) {
                    const int64_t path = lane.path[k];
                    float *th = Th + 3 * path;
                    for (int c = 0; c < 3; ++c) th[c] = weight[c][k];
                    Pb[path] = pdf[k];
                    for (int c = 0; c < 3; ++c) {  // branchless compaction: kept when the weight is positive
                        Bo[3 * nbounce + c] = lane.P[c][k] + lane.n[c][k] * eps_;
                        Bd[3 * nbounce + c] = wi[c][k];
                    }
                    Bp[nbounce] = (int32_t)path;
                    nbounce += (max3(th) > 0.0f);
                }
            }
        }
        return {ns, nbounce};
    }

    // ---- stage shade_x2: after intersect_bounce --------------------------------------------------------------
    int64_t shade2(In<uint64_t> keys, In<float> b_o, In<float> b_d, In<int32_t> b_path, In<float> t2,
                   In<int32_t> prim2, In<float> pdfb, Out<float> E2, Out<uint8_t> hit2, Out<float> sh_o,
                   Out<float> sh_d, Out<float> sh_t, Out<float> sh_val, Out<int32_t> sh_path, int64_t offset) {
        const int64_t N = keys.shape(0), nbounce = b_path.shape(0);
        check_rows(b_o, "b_o", nbounce, 3); check_rows(b_d, "b_d", nbounce, 3);
        check_rows(t2, "t2", nbounce, 0); check_rows(prim2, "prim2", nbounce, 0);
        check_rows(pdfb, "pdfb", N, 0); check_rows(E2, "E2", N, 3); check_rows(hit2, "hit2", N, 0);
        ShadowBuf sb = shadow_buf(sh_o, sh_d, sh_t, sh_val, sh_path);
        if (offset < 0 || sb.cap < offset + nbounce) throw std::invalid_argument("shade2: shadow buffers too small");
        check_prims(prim2.data(), nbounce);
        for (int64_t j = 0; j < nbounce; ++j)
            if (b_path.data()[j] < 0 || b_path.data()[j] >= N) throw std::invalid_argument("shade2: bad b_path");
        int64_t ns = offset;
        {
            nb::gil_scoped_release release;
            const uint64_t *K = keys.data();
            const float *Bo = b_o.data(), *Bd = b_d.data(), *T2 = t2.data(), *Pb = pdfb.data();
            const int32_t *Bp = b_path.data(), *Pr = prim2.data();
            float *E = E2.data();
            uint8_t *H = hit2.data();
            std::fill(E, E + 3 * N, 0.0f);
            std::fill(H, H + N, (uint8_t)0);
            Lanes lane;
            NeeBlock res;
            for (int64_t j0 = 0; j0 < nbounce; j0 += kBlock) {
                const int64_t j1 = std::min<int64_t>(nbounce, j0 + kBlock);
                int m = 0;
                for (int64_t j = j0; j < j1; ++j) {
                    if (Pr[j] < 0) continue;
                    const int64_t i = Bp[j];
                    H[i] = 1;
                    const float *dj = Bd + 3 * j, *oj = Bo + 3 * j;
                    const float t = T2[j];
                    float P[3], n[3], wo[3];
                    for (int c = 0; c < 3; ++c) P[c] = oj[c] + t * dj[c];
                    const int mat = surface(Pr[j], dj, n);
                    for (int c = 0; c < 3; ++c) wo[c] = -dj[c];
                    lane.set(m++, P, n, wo, mat, K[i], i);
                    if (mat_emissive_.data()[mat]) {  // MIS-weighted emission of x2
                        const float *e = emission_.data() + 3 * mat;
                        float *ei = E + 3 * i;
                        if (!lights_empty_) {
                            const float cos_l = std::fabs(dot3(face_normal_.data() + 3 * Pr[j], dj));
                            const float pdf_l = pdf_area_face_.data()[Pr[j]] * t * t / maxlo(cos_l, 1e-12f);
                            const float pb = Pb[i];
                            const float w = (pb > 0.0f) ? pb / (pb + pdf_l) : 0.0f;
                            for (int c = 0; c < 3; ++c) ei[c] = e[c] * w;
                        } else {
                            for (int c = 0; c < 3; ++c) ei[c] = e[c];
                        }
                    }
                }
                if (!lights_empty_) {  // NEE at x2
                    nee_block(m, lane, L2, L2U, L2V, false, res);
                    for (int k = 0; k < m; ++k) {
                        push_shadow(sb, ns, res, k, (int32_t)lane.path[k]);
                        ns += res.ok[k];
                    }
                }
            }
        }
        return ns - offset;
    }

    // ---- stage accumulate: after intersect_shadow ------------------------------------------------------------
    void accumulate(In<int32_t> prim, In<uint8_t> hit2, In<float> thr, In<float> E2, In<int32_t> sh_path,
                    In<float> sh_val, In<bool> occluded, int64_t n_first, float limit, bool clamp, Out<float> L) {
        const int64_t N = prim.shape(0), ns = occluded.shape(0);
        check_rows(hit2, "hit2", N, 0); check_rows(thr, "thr", N, 3); check_rows(E2, "E2", N, 3);
        check_rows(L, "L", N, 3); check_rows(sh_path, "sh_path", ns, 0); check_rows(sh_val, "sh_val", ns, 3);
        if (n_first < 0 || n_first > ns) throw std::invalid_argument("accumulate: n_first out of range");
        for (int64_t s = 0; s < ns; ++s)
            if (sh_path.data()[s] < 0 || sh_path.data()[s] >= N) throw std::invalid_argument("accumulate: bad sh_path");
        for (int64_t s = 1; s < ns; ++s)  // each set holds at most one ray per path, in path order (shade1/shade2)
            if (s != n_first && sh_path.data()[s] <= sh_path.data()[s - 1])
                throw std::invalid_argument("accumulate: shadow rays of a set must be in increasing path order");
        {
            nb::gil_scoped_release release;
            const int32_t *Sp = sh_path.data(), *Pr = prim.data();
            const float *Sv = sh_val.data(), *Th = thr.data(), *E = E2.data();
            const bool *occ = occluded.data();
            const uint8_t *H = hit2.data();
            float *Lo = L.data();
            // The numpy reference scatters the visible shadow values into per-path sums R1 (x1) and R2 (x2) that
            // start at 0; with one ray per path and set, a path's sum is 0 + its ray's value. The two sets are
            // walked alongside the paths instead (s1, s2), which needs no per-path arrays.
            int64_t s1 = 0, s2 = n_first;
            for (int64_t i = 0; i < N; ++i) {
                float r1[3] = {0.0f, 0.0f, 0.0f}, r2[3] = {0.0f, 0.0f, 0.0f};
                if (s1 < n_first && Sp[s1] == i) {
                    if (!occ[s1])
                        for (int c = 0; c < 3; ++c) r1[c] += Sv[3 * s1 + c];
                    ++s1;
                }
                if (s2 < ns && Sp[s2] == i) {
                    if (!occ[s2])
                        for (int c = 0; c < 3; ++c) r2[c] += Sv[3 * s2 + c];
                    ++s2;
                }
                if (Pr[i] < 0) continue;
                if (H[i]) {
                    if (clamp) clamp_row(r2, limit);
                    for (int c = 0; c < 3; ++c) r1[c] += Th[3 * i + c] * (E[3 * i + c] + r2[c]);
                }
                if (clamp) clamp_row(r1, limit);
                for (int c = 0; c < 3; ++c) Lo[3 * i + c] += r1[c];
            }
        }
    }

    // Single-purpose entry points for the per-stage parity tests.
    void bsdf_sample_batch(In<int32_t> mat, In<float> n, In<float> wo, In<uint64_t> keys, Out<float> wi,
                           Out<float> weight, Out<float> pdf) {
        const int64_t N = mat.shape(0);
        check_rows(n, "n", N, 3); check_rows(wo, "wo", N, 3); check_rows(keys, "keys", N, 0);
        check_rows(wi, "wi", N, 3); check_rows(weight, "weight", N, 3); check_rows(pdf, "pdf", N, 0);
        check_mats(mat.data(), N);
        for (int64_t i = 0; i < N; ++i)
            bsdf_sample(mat.data()[i], n.data() + 3 * i, wo.data() + 3 * i, keys.data()[i], wi.data() + 3 * i,
                        weight.data() + 3 * i, pdf.data()[i]);
    }

    void nee_batch(In<float> P, In<float> n, In<float> wo, In<int32_t> mat, In<uint64_t> keys, int second,
                   bool mis, Out<bool> ok, Out<float> o, Out<float> wi, Out<float> tmax, Out<float> val) {
        const int64_t N = mat.shape(0);
        check_rows(P, "P", N, 3); check_rows(n, "n", N, 3); check_rows(wo, "wo", N, 3);
        check_rows(keys, "keys", N, 0); check_rows(ok, "ok", N, 0); check_rows(o, "o", N, 3);
        check_rows(wi, "wi", N, 3); check_rows(tmax, "tmax", N, 0); check_rows(val, "val", N, 3);
        check_mats(mat.data(), N);
        if (lights_empty_) throw std::invalid_argument("nee_batch: the light set is empty");
        Lanes lane;
        NeeBlock res;
        for (int64_t i0 = 0; i0 < N; i0 += kBlock) {
            const int m = (int)std::min<int64_t>(kBlock, N - i0);
            for (int k = 0; k < m; ++k) {
                const int64_t i = i0 + k;
                lane.set(k, P.data() + 3 * i, n.data() + 3 * i, wo.data() + 3 * i, mat.data()[i], keys.data()[i], i);
            }
            nee_block(m, lane, second ? L2 : L1, second ? L2U : L1U, second ? L2V : L1V, mis, res);
            for (int k = 0; k < m; ++k) {
                const int64_t i = i0 + k;
                ok.data()[i] = res.ok[k] != 0;
                tmax.data()[i] = res.tmax[k];
                for (int c = 0; c < 3; ++c) {
                    o.data()[3 * i + c] = res.o[c][k];
                    wi.data()[3 * i + c] = res.wi[c][k];
                    val.data()[3 * i + c] = res.val[c][k];
                }
            }
        }
    }

private:
    In<float> face_normal_;
    In<int32_t> face_material_;
    In<float> kd_, ks_, exponent_, p_spec_, emission_;
    In<bool> mat_emissive_;
    In<double> cdf_, prob_;
    In<float> table_, point_pos_, point_int_, pdf_area_face_;
    float eps_;
    bool glossy_, lights_empty_;
    int64_t num_area_;

    void check_prims(const int32_t *p, int64_t n) const {
        const int64_t F = face_normal_.shape(0);
        for (int64_t i = 0; i < n; ++i)
            if (p[i] >= F) throw std::invalid_argument("tracer kernels: primitive index out of range");
    }
    void check_mats(const int32_t *m, int64_t n) const {
        const int64_t M = kd_.shape(0);
        for (int64_t i = 0; i < n; ++i)
            if (m[i] < 0 || m[i] >= M) throw std::invalid_argument("tracer kernels: material index out of range");
    }

    static ShadowBuf shadow_buf(Out<float> &o, Out<float> &d, Out<float> &t, Out<float> &val, Out<int32_t> &path) {
        const int64_t cap = path.shape(0);
        check_rows(o, "sh_o", cap, 3); check_rows(d, "sh_d", cap, 3); check_rows(t, "sh_t", cap, 0);
        check_rows(val, "sh_val", cap, 3);
        return {o.data(), d.data(), t.data(), val.data(), path.data(), cap};
    }
    static void push_shadow(ShadowBuf &sb, int64_t k, const NeeBlock &r, int lane, int32_t path) {
        for (int c = 0; c < 3; ++c) {
            sb.o[3 * k + c] = r.o[c][lane];
            sb.d[3 * k + c] = r.wi[c][lane];
            sb.val[3 * k + c] = r.val[c][lane];
        }
        sb.t[k] = r.tmax[lane];
        sb.path[k] = path;
    }
    // tracer._clamp_radiance for one row, without branches (which channel is largest is a coin toss, so a branch
    // mispredicts). Where max3 matters it is the largest channel: a NaN channel makes max3 NaN, never above the
    // limit; ties and the sign of zero do not matter (max > limit > 0).
    static void clamp_row(float *r, float limit) {
        const bool nan = (r[0] != r[0]) || (r[1] != r[1]) || (r[2] != r[2]);
        const float m01 = (r[1] > r[0]) ? r[1] : r[0];
        const float m = (r[2] > m01) ? r[2] : m01;
        const bool over = (m > limit) && !nan;
        const float s = limit / m;
        for (int c = 0; c < 3; ++c) {
            const float scaled = r[c] * s;
            r[c] = over ? scaled : r[c];
        }
    }

    // PathTracer._surface: material id, shading normal facing against d.
    int surface(int32_t prim, const float *d, float *n) const {
        const float *fn = face_normal_.data() + 3 * prim;
        const float sign = (dot3(fn, d) > 0.0f) ? -1.0f : 1.0f;
        for (int c = 0; c < 3; ++c) n[c] = fn[c] * sign;
        return face_material_.data()[prim];
    }

    // PathTracer._bsdf_eval (bsdf.mixture_eval / phong_eval for glossy scenes): f, cos_i, pdf.
    void bsdf_eval(int mat, const float *n, const float *wo, const float *wi, float *f, float &cos_i,
                   float &pdf) const {
        const float *kd = kd_.data() + 3 * mat;
        cos_i = dot3(n, wi);
        if (!glossy_) {
            for (int c = 0; c < 3; ++c) f[c] = kd[c] * kInvPi;
            pdf = max0(cos_i) * kInvPi;
            return;
        }
        const float *ks = ks_.data() + 3 * mat;
        const float e = exponent_.data()[mat], ps = p_spec_.data()[mat];
        float r[3];
        reflect(n, wo, r);
        const float cr = max0(dot3(r, wi));
        const float base = fpow(cr, e) * kInvTwoPi;
        const float fs = base * (e + 2.0f);
        const float pdf_s = base * (e + 1.0f);
        for (int c = 0; c < 3; ++c) f[c] = kd[c] * kInvPi + ks[c] * fs;
        pdf = (1.0f - ps) * (max0(cos_i) * kInvPi) + ps * pdf_s;
    }

    // PathTracer._bsdf_sample: direction, weight f cos / pdf (0 when invalid), pdf.
    void bsdf_sample(int mat, const float *n, const float *wo, uint64_t key, float *wi, float *weight,
                     float &pdf) const {
        const float u1 = sr_rng::uniform(key, BU), u2 = sr_rng::uniform(key, BV);
        float cph, sph;
        unit_circle(u2, cph, sph);
        const float *kd = kd_.data() + 3 * mat;
        if (!glossy_) {  // bsdf.lambert_sample
            const float r = std::sqrt(u1);
            const float cz = std::sqrt(max0(1.0f - u1));
            to_world(n, r * cph, r * sph, cz, wi);
            const float ok = (cz > 0.0f) ? 1.0f : 0.0f;
            for (int c = 0; c < 3; ++c) weight[c] = kd[c] * ok;
            pdf = max0(cz) * kInvPi;
            return;
        }
        // bsdf.mixture_sample
        const float u_lobe = sr_rng::uniform(key, LOBE);
        if (u_lobe < p_spec_.data()[mat]) {  // bsdf.phong_sample
            const float e = exponent_.data()[mat];
            float r[3];
            reflect(n, wo, r);
            const float ca = fpow(u1, 1.0f / (e + 1.0f));
            const float sa = std::sqrt(max0(1.0f - ca * ca));
            to_world(r, sa * cph, sa * sph, ca, wi);
        } else {
            const float r = std::sqrt(u1);
            const float cz = std::sqrt(max0(1.0f - u1));
            to_world(n, r * cph, r * sph, cz, wi);
        }
        float f[3], cos_i;
        bsdf_eval(mat, n, wo, wi, f, cos_i, pdf);
        const bool ok = (cos_i > 0.0f) && (pdf > 0.0f);
        const float scale = ok ? cos_i / pdf : 0.0f;
        for (int c = 0; c < 3; ++c) weight[c] = f[c] * scale;
    }

    // bsdf_sample for the m lanes of a block: Lambertian scenes as vectorised loops (bsdf.lambert_sample), glossy
    // ones lane by lane (their pow is a float64 libm call).
    void bsdf_sample_block(int m, const Lanes &in, float (*wi)[kBlock], float (*weight)[kBlock], float *pdf) const {
        if (glossy_) {
            for (int k = 0; k < m; ++k) {
                float P[3], n[3], wo[3], w[3], wk[3];
                in.get(k, P, n, wo);
                bsdf_sample(in.mat[k], n, wo, in.key[k], w, wk, pdf[k]);
                for (int c = 0; c < 3; ++c) {
                    wi[c][k] = w[c];
                    weight[c][k] = wk[c];
                }
            }
            return;
        }
        float u1[kBlock], u2[kBlock], kd[3][kBlock];
        for (int k = 0; k < m; ++k) {
            u1[k] = sr_rng::uniform(in.key[k], BU);
            u2[k] = sr_rng::uniform(in.key[k], BV);
            const float *kdm = kd_.data() + 3 * in.mat[k];
            for (int c = 0; c < 3; ++c) kd[c][k] = kdm[c];
        }
#pragma omp simd
        for (int k = 0; k < m; ++k) {
            float cph, sph;
            unit_circle(u2[k], cph, sph);
            const float r = std::sqrt(u1[k]);
            const float cz = std::sqrt(max0(1.0f - u1[k]));
            to_world(in.n[0][k], in.n[1][k], in.n[2][k], r * cph, r * sph, cz, wi[0][k], wi[1][k], wi[2][k]);
            const bool up = cz > 0.0f;
            const float ok = up ? 1.0f : 0.0f;
            for (int c = 0; c < 3; ++c) weight[c][k] = kd[c][k] * ok;
            pdf[k] = max0(cz) * kInvPi;
        }
    }

    // PathTracer._nee with LightSet.sample: one light sample at each of m <= kBlock shading points. Every step is
    // a loop over the block's lanes, in structure-of-arrays form: the hashing and light selection are scalar
    // integer work, the geometry and the values are float loops the compiler vectorises (omp simd: 4 or 8 lanes per
    // instruction, the same IEEE operations per lane as numpy's, in the same order).
    void nee_block(int m, const Lanes &in, uint64_t d_sel, uint64_t d_u, uint64_t d_v, bool mis, NeeBlock &r) const {
        LightLanes s;
        select_lights(m, in, d_sel, d_u, d_v, s);
        const bool any_point = light_points(m, s);
        shadow_rays(m, in, s, r);
        if (any_point) point_light_values(m, s);
        nee_bsdf(m, in, r, s);
        nee_values(m, mis, s, r);
    }

    // (1) random numbers and light selection: np.searchsorted(cdf, u, side="right"), clipped to the last light.
    void select_lights(int m, const Lanes &in, uint64_t d_sel, uint64_t d_u, uint64_t d_v, LightLanes &s) const {
        const int64_t K = cdf_.shape(0);
        const double *cdf = cdf_.data();
        for (int k = 0; k < m; ++k) {
            const double u = static_cast<double>(sr_rng::uniform(in.key[k], d_sel));
            s.u1[k] = sr_rng::uniform(in.key[k], d_u);
            s.u2[k] = sr_rng::uniform(in.key[k], d_v);
            int64_t c = 0;
            if (K <= 32) {  // branchless count of cdf entries <= u (= upper_bound on the sorted CDF)
                for (int64_t q = 0; q < K; ++q) c += (cdf[q] <= u);
            } else {
                c = std::upper_bound(cdf, cdf + K, u) - cdf;
            }
            s.sel[k] = static_cast<int32_t>(std::min<int64_t>(c, K - 1));
        }
    }

    // (2) the selected light's data per lane: sampled point, normal, emission and area pdf factor (area lights),
    // position (point lights, whose value point_light_values sets). Returns whether any lane chose a point light.
    bool light_points(int m, LightLanes &s) const {
        bool any_point = false;
        for (int k = 0; k < m; ++k) {
            if (s.sel[k] < num_area_) {
                const float *T = table_.data() + 16 * s.sel[k];
                const float su = std::sqrt(s.u1[k]);
                const float b1 = su * (1.0f - s.u2[k]), b2 = su * s.u2[k];
                for (int c = 0; c < 3; ++c) {
                    s.target[c][k] = T[c] + b1 * T[3 + c] + b2 * T[6 + c];
                    s.ln[c][k] = T[9 + c];
                    s.le[c][k] = T[12 + c];
                }
                s.lpdf[k] = T[15];
            } else {
                const float *p = point_pos_.data() + 3 * (s.sel[k] - num_area_);
                for (int c = 0; c < 3; ++c) {
                    s.target[c][k] = p[c];
                    s.ln[c][k] = s.le[c][k] = 0.0f;
                }
                s.lpdf[k] = 0.0f;
                any_point = true;
            }
        }
        return any_point;
    }

    // (3) shadow ray (origin offset along the normal, unit direction to the light point) and the area light's
    // value and pdf per solid angle (infinite where the light is seen edge-on or the points coincide).
    void shadow_rays(int m, const Lanes &in, LightLanes &s, NeeBlock &r) const {
        const float eps = eps_;
#pragma omp simd
        for (int k = 0; k < m; ++k) {
            float delta[3];
            for (int c = 0; c < 3; ++c) {
                const float o = in.P[c][k] + in.n[c][k] * eps;
                r.o[c][k] = o;
                delta[c] = s.target[c][k] - o;
            }
            const float q = delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2];
            const float len = std::sqrt(q);
            const float safe = (len > 0.0f) ? len : 1.0f;
            float wi[3];
            for (int c = 0; c < 3; ++c) {
                wi[c] = delta[c] / safe;
                r.wi[c][k] = wi[c];
            }
            const float cos_l = std::fabs(s.ln[0][k] * wi[0] + s.ln[1][k] * wi[1] + s.ln[2][k] * wi[2]);
            const float pdf_a = s.lpdf[k] * q / maxlo(cos_l, 1e-12f);
            const bool facing = cos_l > 1e-7f, apart = q > 0.0f;  // (named first: no branch, the loop vectorises)
            const bool ok = facing && apart;
            s.pdf_l[k] = ok ? pdf_a : kInf;
            const float inv_a = 1.0f / pdf_a;  // computed for every lane, selected below (a select vectorises)
            const float inv = ok ? inv_a : 0.0f;
            for (int c = 0; c < 3; ++c) s.li[c][k] = s.le[c][k] * inv;
            s.d2[k] = q;
            s.dist[k] = len;
        }
    }

    // (4) point lights' values (LightSet.sample: intensity / (d^2 prob) in float64, no MIS).
    void point_light_values(int m, LightLanes &s) const {
        for (int k = 0; k < m; ++k) {
            if (s.sel[k] < num_area_) continue;
            const int64_t q = s.sel[k] - num_area_;
            const float w = (s.d2[k] > 0.0f)
                ? static_cast<float>(1.0 / (static_cast<double>(s.d2[k]) * prob_.data()[num_area_ + q])) : 0.0f;
            const float *I = point_int_.data() + 3 * q;
            for (int c = 0; c < 3; ++c) s.li[c][k] = I[c] * w;
            s.pdf_l[k] = kInf;
        }
    }

    // (5) the BSDF at the shading point towards the light: f, cos_i, pdf (bsdf.lambert_eval as vectorised loops;
    // the glossy mixture lane by lane, its pow being a float64 libm call).
    void nee_bsdf(int m, const Lanes &in, const NeeBlock &r, LightLanes &s) const {
        if (glossy_) {
            for (int k = 0; k < m; ++k) {
                float n[3], wo[3], wi[3], fk[3];
                for (int c = 0; c < 3; ++c) {
                    n[c] = in.n[c][k];
                    wo[c] = in.wo[c][k];
                    wi[c] = r.wi[c][k];
                }
                bsdf_eval(in.mat[k], n, wo, wi, fk, s.cos_i[k], s.pdf_b[k]);
                for (int c = 0; c < 3; ++c) s.f[c][k] = fk[c];
            }
            return;
        }
        for (int k = 0; k < m; ++k) {
            const float *kd = kd_.data() + 3 * in.mat[k];
            for (int c = 0; c < 3; ++c) s.f[c][k] = kd[c] * kInvPi;
        }
#pragma omp simd
        for (int k = 0; k < m; ++k) {
            const float ci = in.n[0][k] * r.wi[0][k] + in.n[1][k] * r.wi[1][k] + in.n[2][k] * r.wi[2][k];
            s.cos_i[k] = ci;
            s.pdf_b[k] = max0(ci) * kInvPi;
        }
    }

    // (6) MIS weight, value, and whether the shadow ray is needed at all.
    void nee_values(int m, bool mis, const LightLanes &s, NeeBlock &r) const {
        const float two_eps = 2.0f * eps_;
        const bool no_mis = !mis;
#pragma omp simd
        for (int k = 0; k < m; ++k) {
            const float cpos = max0(s.cos_i[k]);
            const float w_mis = s.pdf_l[k] / (s.pdf_l[k] + s.pdf_b[k]);
            const bool single = std::fabs(s.pdf_l[k]) == kInf;  // delta light (or no valid light pdf): weight 1
            const float w = (no_mis || single) ? 1.0f : w_mis;  // x * 1 is x, bit for bit: no MIS = weight 1
            float v[3];
            for (int c = 0; c < 3; ++c) {
                v[c] = s.f[c][k] * (s.li[c][k] * cpos) * w;
                r.val[c][k] = v[c];
            }
            const bool lit = s.cos_i[k] > 0.0f, far = s.dist[k] > two_eps;
            r.ok[k] = (lit && far && max3_positive(v[0], v[1], v[2])) ? 1 : 0;
            r.tmax[k] = s.dist[k] - two_eps;
        }
    }
};

// ---- stage generate: keys and primary rays ------------------------------------------------------------------
void tracer_generate(uint64_t key, int64_t width, In<int64_t> pix, In<int64_t> samp, In<float> M, In<float> center,
                     Out<uint64_t> keys, Out<float> o, Out<float> d) {
    const int64_t N = pix.shape(0);
    check_rows(samp, "samp", N, 0); check_rows(M, "M", 9, 0); check_rows(center, "center", 3, 0);
    check_rows(keys, "keys", N, 0); check_rows(o, "o", N, 3); check_rows(d, "d", N, 3);
    if (width < 1) throw std::invalid_argument("tracer_generate: width must be >= 1");
    for (int64_t i = 0; i < N; ++i)
        if (pix.data()[i] < 0 || samp.data()[i] < 0)
            throw std::invalid_argument("tracer_generate: pixel and sample indices must be >= 0");
    nb::gil_scoped_release release;
    const int64_t *P = pix.data(), *S = samp.data();
    const float *m = M.data(), *C = center.data();
    uint64_t *Ko = keys.data();
    float *O = o.data(), *D = d.data();
    for (int64_t i = 0; i < N; ++i) {
        const uint64_t k = sr_rng::path_key(key, P[i], S[i]);
        Ko[i] = k;
        const float px = static_cast<float>(P[i] % width) + sr_rng::uniform(k, JX);
        const float py = static_cast<float>(P[i] / width) + sr_rng::uniform(k, JY);
        float v[3];
        for (int r = 0; r < 3; ++r) v[r] = m[3 * r] * px + m[3 * r + 1] * py + m[3 * r + 2];
        const float len = std::sqrt(dot3(v, v));
        const float s = (len > 0.0f) ? len : 1.0f;
        for (int c = 0; c < 3; ++c) {
            D[3 * i + c] = v[c] / s;
            O[3 * i + c] = C[c];
        }
    }
}

// G-buffer rays (PathTracer._gbuffer): unjittered, through pixel centres, direction with camera z = 1 (not unit).
void tracer_gbuffer_rays(int64_t width, In<int64_t> pix, In<float> M, In<float> center, Out<float> o, Out<float> d) {
    const int64_t N = pix.shape(0);
    check_rows(M, "M", 9, 0); check_rows(center, "center", 3, 0); check_rows(o, "o", N, 3); check_rows(d, "d", N, 3);
    if (width < 1) throw std::invalid_argument("tracer_gbuffer_rays: width must be >= 1");
    for (int64_t i = 0; i < N; ++i)
        if (pix.data()[i] < 0) throw std::invalid_argument("tracer_gbuffer_rays: pixel indices must be >= 0");
    nb::gil_scoped_release release;
    const int64_t *P = pix.data();
    const float *m = M.data(), *C = center.data();
    float *O = o.data(), *D = d.data();
    for (int64_t i = 0; i < N; ++i) {
        const float px = static_cast<float>(P[i] % width) + 0.5f;
        const float py = static_cast<float>(P[i] / width) + 0.5f;
        for (int r = 0; r < 3; ++r) {
            D[3 * i + r] = m[3 * r] * px + m[3 * r + 1] * py + m[3 * r + 2];
            O[3 * i + r] = C[r];
        }
    }
}

// G-buffer values of the hits (PathTracer._gbuffer): planar (C, H*W) images, written only at hit pixels.
void tracer_gbuffer_write(In<int64_t> pix, In<float> d, In<float> t, In<int32_t> prim, In<float> center,
                          In<float> face_normal, In<int32_t> face_material, In<float> kd, Out<float> depth,
                          Out<float> normal, Out<float> position, Out<float> albedo, Out<int32_t> material_id) {
    const int64_t N = pix.shape(0), F = face_normal.shape(0), M = kd.shape(0), HW = depth.shape(0);
    check_rows(d, "d", N, 3); check_rows(t, "t", N, 0); check_rows(prim, "prim", N, 0);
    check_rows(center, "center", 3, 0); check_rows(face_normal, "face_normal", F, 3);
    check_rows(face_material, "face_material", F, 0); check_rows(kd, "kd", M, 3);
    check_rows(normal, "normal", 3, HW); check_rows(position, "position", 3, HW); check_rows(albedo, "albedo", 3, HW);
    check_rows(material_id, "material_id", HW, 0);
    for (int64_t i = 0; i < N; ++i) {
        if (pix.data()[i] < 0 || pix.data()[i] >= HW || prim.data()[i] >= F)
            throw std::invalid_argument("tracer_gbuffer_write: pixel or primitive index out of range");
        if (prim.data()[i] >= 0 && (face_material.data()[prim.data()[i]] < 0 ||
                                    face_material.data()[prim.data()[i]] >= M))
            throw std::invalid_argument("tracer_gbuffer_write: material index out of range");
    }
    nb::gil_scoped_release release;
    const float *FN = face_normal.data(), *Kd = kd.data(), *C = center.data();
    for (int64_t i = 0; i < N; ++i) {
        const int32_t pr = prim.data()[i];
        if (pr < 0) continue;
        const int64_t p = pix.data()[i];
        const float *di = d.data() + 3 * i, *fn = FN + 3 * pr;
        const float ti = t.data()[i];
        const float sign = (dot3(fn, di) > 0.0f) ? -1.0f : 1.0f;
        const int32_t mat = face_material.data()[pr];
        depth.data()[p] = ti;
        for (int c = 0; c < 3; ++c) {
            normal.data()[c * HW + p] = fn[c] * sign;
            position.data()[c * HW + p] = C[c] + ti * di[c];
            albedo.data()[c * HW + p] = Kd[3 * mat + c];
        }
        material_id.data()[p] = mat;
    }
}

void rng_path_keys(uint64_t key, In<int64_t> pixel, In<int64_t> sample, Out<uint64_t> out) {
    const int64_t N = pixel.shape(0);
    check_rows(sample, "sample", N, 0); check_rows(out, "out", N, 0);
    nb::gil_scoped_release release;
    for (int64_t i = 0; i < N; ++i) out.data()[i] = sr_rng::path_key(key, pixel.data()[i], sample.data()[i]);
}

void rng_uniform(In<uint64_t> keys, uint64_t dim, Out<float> out) {
    const int64_t N = keys.shape(0);
    check_rows(out, "out", N, 0);
    nb::gil_scoped_release release;
    for (int64_t i = 0; i < N; ++i) out.data()[i] = sr_rng::uniform(keys.data()[i], dim);
}

}  // namespace

void bind_shade_tracer(nb::module_ &m) {
    using nb::arg;
    m.def("tracer_generate", &tracer_generate, arg("key"), arg("width"), arg("pix").noconvert(),
          arg("samp").noconvert(), arg("M").noconvert(), arg("center").noconvert(), arg("keys").noconvert(),
          arg("o").noconvert(), arg("d").noconvert(),
          "Path keys and primary rays (origins = centre, unit directions through jittered pixel positions).");
    m.def("tracer_gbuffer_rays", &tracer_gbuffer_rays, arg("width"), arg("pix").noconvert(), arg("M").noconvert(),
          arg("center").noconvert(), arg("o").noconvert(), arg("d").noconvert(),
          "G-buffer rays through pixel centres (directions with camera z = 1).");
    m.def("tracer_gbuffer_write", &tracer_gbuffer_write, arg("pix").noconvert(), arg("d").noconvert(),
          arg("t").noconvert(), arg("prim").noconvert(), arg("center").noconvert(), arg("face_normal").noconvert(),
          arg("face_material").noconvert(), arg("kd").noconvert(), arg("depth").noconvert(),
          arg("normal").noconvert(), arg("position").noconvert(), arg("albedo").noconvert(),
          arg("material_id").noconvert(), "G-buffer values at the hit pixels, planar (C, H*W) outputs.");
    m.def("rng_path_keys", &rng_path_keys, arg("key"), arg("pixel").noconvert(), arg("sample").noconvert(),
          arg("out").noconvert(), "rng.path_keys into out (uint64).");
    m.def("rng_uniform", &rng_uniform, arg("keys").noconvert(), arg("dim"), arg("out").noconvert(),
          "rng.uniform into out (float32).");
    nb::class_<TracerShader>(m, "TracerShader",
                             "Scene + light tables of one frame and the shading stages of the path tracer.")
        .def(nb::init<In<float>, In<int32_t>, In<float>, In<float>, In<float>, In<float>, In<float>, In<bool>, float,
                      bool, bool, In<double>, In<double>, In<float>, int64_t, In<float>, In<float>, In<float>>(),
             arg("face_normal").noconvert(), arg("face_material").noconvert(), arg("kd").noconvert(),
             arg("ks").noconvert(), arg("exponent").noconvert(), arg("p_spec").noconvert(),
             arg("emission").noconvert(), arg("mat_emissive").noconvert(), arg("eps"), arg("glossy"),
             arg("lights_empty"), arg("cdf").noconvert(), arg("prob").noconvert(), arg("table").noconvert(),
             arg("num_area"), arg("point_pos").noconvert(), arg("point_int").noconvert(),
             arg("pdf_area_face").noconvert())
        .def("shade1", &TracerShader::shade1, arg("keys").noconvert(), arg("d").noconvert(), arg("t").noconvert(),
             arg("prim").noconvert(), arg("center").noconvert(), arg("L").noconvert(), arg("thr").noconvert(),
             arg("pdfb").noconvert(), arg("sh_o").noconvert(), arg("sh_d").noconvert(), arg("sh_t").noconvert(),
             arg("sh_val").noconvert(), arg("sh_path").noconvert(), arg("b_o").noconvert(), arg("b_d").noconvert(),
             arg("b_path").noconvert(), "Stage after the primary query; returns (shadow rays, bounce rays).")
        .def("shade2", &TracerShader::shade2, arg("keys").noconvert(), arg("b_o").noconvert(),
             arg("b_d").noconvert(), arg("b_path").noconvert(), arg("t2").noconvert(), arg("prim2").noconvert(),
             arg("pdfb").noconvert(), arg("E2").noconvert(), arg("hit2").noconvert(), arg("sh_o").noconvert(),
             arg("sh_d").noconvert(), arg("sh_t").noconvert(), arg("sh_val").noconvert(),
             arg("sh_path").noconvert(), arg("offset"), "Stage after the bounce query; returns its shadow rays.")
        .def("accumulate", &TracerShader::accumulate, arg("prim").noconvert(), arg("hit2").noconvert(),
             arg("thr").noconvert(), arg("E2").noconvert(), arg("sh_path").noconvert(), arg("sh_val").noconvert(),
             arg("occluded").noconvert(), arg("n_first"), arg("limit"), arg("clamp"), arg("L").noconvert(),
             "Stage after the occlusion query: NEE values, clamps, the sample (added to L in place).")
        .def("bsdf_sample", &TracerShader::bsdf_sample_batch, arg("mat").noconvert(), arg("n").noconvert(),
             arg("wo").noconvert(), arg("keys").noconvert(), arg("wi").noconvert(), arg("weight").noconvert(),
             arg("pdf").noconvert(), "PathTracer._bsdf_sample (for parity tests).")
        .def("nee", &TracerShader::nee_batch, arg("P").noconvert(), arg("n").noconvert(), arg("wo").noconvert(),
             arg("mat").noconvert(), arg("keys").noconvert(), arg("second"), arg("mis"), arg("ok").noconvert(),
             arg("o").noconvert(), arg("wi").noconvert(), arg("tmax").noconvert(), arg("val").noconvert(),
             "PathTracer._nee (for parity tests; second=1 uses the x2 dimensions).");
}
