// Counter-based random numbers of the path tracer: the exact C++ twin of stereorepro/render/rng.py.
// A number is fmix(path_key ^ fmix(dim + C0)) >> 40, scaled by 2^-24 (float32 in [0, 1)); path keys fold the
// pixel and sample index into the per-render stream key with h = fmix(h ^ fmix(v + C0)) (splitmix64 finaliser).
// All arithmetic is uint64 with wrap-around, as numpy's uint64 ufuncs do.
#pragma once
#include <cstdint>

namespace sr_rng {

constexpr uint64_t C0 = 0x9E3779B97F4A7C15ull;
constexpr uint64_t C1 = 0xBF58476D1CE4E5B9ull;
constexpr uint64_t C2 = 0x94D049BB133111EBull;

inline uint64_t fmix(uint64_t z) {
    z = (z ^ (z >> 30)) * C1;
    z = (z ^ (z >> 27)) * C2;
    return z ^ (z >> 31);
}

// rng.path_keys(key, pixel, sample) for one path (pixel, sample >= 0 as in the tracer; cast like astype(uint64)).
inline uint64_t path_key(uint64_t key, int64_t pixel, int64_t sample) {
    const uint64_t h = fmix(key ^ fmix(static_cast<uint64_t>(pixel) + C0));
    return fmix(h ^ fmix(static_cast<uint64_t>(sample) + C0));
}

// rng.uniform(keys, dim) for one key: the top 24 bits as float32 (exact) times 2^-24 (exact).
inline float uniform(uint64_t key, uint64_t dim) {
    const uint64_t d = fmix(dim + C0);
    const uint64_t bits = fmix(key ^ d) >> 40;
    return static_cast<float>(bits) * (1.0f / 16777216.0f);
}

}  // namespace sr_rng
