// Temporal blending (the paper's 20 % EMA with BMFR-style warm-up), the native twin of
// stereorepro.reproject.temporal_blend (same rules: n clamped at 0, alpha clamped to [0, 1]). Layout: NCHW float32, C-contiguous.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <algorithm>
#include <cstdint>
#include <stdexcept>

namespace nb = nanobind;

using CF = nb::ndarray<const float, nb::c_contig, nb::device::cpu>;
using CB = nb::ndarray<const bool, nb::c_contig, nb::device::cpu>;
using OF = nb::ndarray<float, nb::c_contig, nb::device::cpu>;

static void temporal_blend(CF current, CF history, CF history_len, CB valid, float alpha, bool warmup,
                           float max_history, OF out_color, OF out_len) {
    if (current.ndim() != 4 || history.ndim() != 4 || history_len.ndim() != 4 || valid.ndim() != 4 ||
        out_color.ndim() != 4 || out_len.ndim() != 4)
        throw std::invalid_argument("temporal_blend: all arrays must be 4-D (B, C, H, W)");
    const int64_t B = current.shape(0), C = current.shape(1), H = current.shape(2), W = current.shape(3);
    for (size_t d = 0; d < 4; ++d) {
        if (history.shape(d) != current.shape(d) || out_color.shape(d) != current.shape(d))
            throw std::invalid_argument("temporal_blend: history/out_color must match current's shape");
    }
    const int64_t hw = H * W;
    if (history_len.shape(0) != B || history_len.shape(1) != 1 || history_len.shape(2) != H || history_len.shape(3) != W ||
        valid.shape(0) != B || valid.shape(1) != 1 || valid.shape(2) != H || valid.shape(3) != W ||
        out_len.shape(0) != B || out_len.shape(1) != 1 || out_len.shape(2) != H || out_len.shape(3) != W)
        throw std::invalid_argument("temporal_blend: history_len/valid/out_len must be (B, 1, H, W)");
    const float *cur = current.data(), *hist = history.data(), *len = history_len.data();
    const bool *val = valid.data();
    float *oc = out_color.data(), *ol = out_len.data();
    {
        nb::gil_scoped_release release;
#ifdef STEREOREPRO_OPENMP
#pragma omp parallel for schedule(static)
#endif
        for (int64_t i = 0; i < B * hw; ++i) {
            const int64_t b = i / hw, p = i % hw;
            const bool v = val[i];
            const float n = v ? std::max(len[i], 0.0f) : 0.0f;
            const float a_min = std::min(std::max(alpha, 0.0f), 1.0f);
            const float a = v ? (warmup ? std::max(1.0f / (n + 1.0f), a_min) : a_min) : 1.0f;
            for (int64_t c = 0; c < C; ++c) {
                const int64_t k = (b * C + c) * hw + p;
                // a == 1 must give exactly the current sample, even if history is not finite.
                oc[k] = (a >= 1.0f) ? cur[k] : (1.0f - a) * hist[k] + a * cur[k];
            }
            ol[i] = v ? std::min(n + 1.0f, max_history) : 1.0f;
        }
    }
}

void bind_blend(nb::module_ &m) {
    m.def("temporal_blend", &temporal_blend, nb::arg("current"), nb::arg("history"), nb::arg("history_len"),
          nb::arg("valid"), nb::arg("alpha"), nb::arg("warmup"), nb::arg("max_history"),
          nb::arg("out_color").noconvert(), nb::arg("out_len").noconvert(),
          "EMA blend of a reprojected history with the current frame; writes out_color, out_len in place.");
}
