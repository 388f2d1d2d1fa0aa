// Fused CPU kernels of the multi-resolution hash-grid encoding (HashGridEncoding), forward and
// backward, parallel over points with OpenMP. Compiled and loaded at first use by native.py
// (plain C ABI through ctypes); HashGridEncoding's pure-PyTorch path is the reference that the
// tests hold this against.
//
// Levels: level l has res[l] cells per axis over [0, 1]^3 (vertex i at i / res[l]). A dense level
// (dense[l] = 1) is a volume of (res + 1)^3 vertices stored as grid_sample's (F, D, H, W) =
// (F, z, y, x); a hashed level is `table_size` rows of F features, row = hash(corner) &
// (table_size - 1) with Instant-NGP's primes (1, 2654435761, 805459861): the low bits of the
// 32-bit products equal those of PyTorch's 64-bit ones. params[l] points at the level's data.
// Output: out[b, l * F + f], levels in order.

#include <cmath>
#include <cstdint>

namespace {

struct Corners {
    int64_t index[8];  // element offset of feature 0 of each corner
    float weight[8];
    float dweight[8][3];  // d weight / d frac along x, y, z
    int64_t feature_stride;
};

inline void corners(const float* p, int res, bool dense, int64_t table_size, int features, Corners& c) {
    float frac[3];
    int64_t base[3];
    for (int a = 0; a < 3; ++a) {
        float pos = p[a] * static_cast<float>(res);
        float f = std::floor(pos);
        if (f > static_cast<float>(res - 1)) f = static_cast<float>(res - 1);  // x = 1 uses the last cell
        base[a] = static_cast<int64_t>(f);
        frac[a] = pos - f;
    }
    const int64_t verts = res + 1;
    c.feature_stride = dense ? verts * verts * verts : 1;
    for (int k = 0; k < 8; ++k) {  // corner k = 4 dz + 2 dy + dx
        const int dx = k & 1, dy = (k >> 1) & 1, dz = (k >> 2) & 1;
        const int64_t x = base[0] + dx, y = base[1] + dy, z = base[2] + dz;
        if (dense) {
            c.index[k] = (z * verts + y) * verts + x;
        } else {
            const uint32_t h = static_cast<uint32_t>(x) ^ (static_cast<uint32_t>(y) * 2654435761u) ^
                               (static_cast<uint32_t>(z) * 805459861u);
            c.index[k] = static_cast<int64_t>(h & static_cast<uint32_t>(table_size - 1)) * features;
        }
        const float wx = dx ? frac[0] : 1.0f - frac[0];
        const float wy = dy ? frac[1] : 1.0f - frac[1];
        const float wz = dz ? frac[2] : 1.0f - frac[2];
        c.weight[k] = wz * wy * wx;
        const float sx = dx ? 1.0f : -1.0f, sy = dy ? 1.0f : -1.0f, sz = dz ? 1.0f : -1.0f;
        c.dweight[k][0] = wz * wy * sx;
        c.dweight[k][1] = wz * sy * wx;
        c.dweight[k][2] = sz * wy * wx;
    }
}

constexpr int kMaxLevels = 32;  // HashGridEncoding's levels; the Python side checks
constexpr int kLookahead = 8;   // points whose corners the backward prefetches ahead

inline void prefetch(const float* data, const Corners& c, int features) {
    for (int k = 0; k < 8; ++k) {
        __builtin_prefetch(data + c.index[k]);
        if (c.feature_stride != 1)  // dense levels keep each feature in its own volume
            for (int f = 1; f < features; ++f) __builtin_prefetch(data + c.index[k] + f * c.feature_stride);
    }
}

}  // namespace

extern "C" {

void hashgrid_forward(const float* x, int64_t n, int n_levels, const int* res, const int* dense,
                      const float* const* params, int64_t table_size, int features, float* out, int n_threads) {
#pragma omp parallel num_threads(n_threads)
    {
        Corners c[kMaxLevels];
#pragma omp for schedule(static)
        for (int64_t b = 0; b < n; ++b) {
            // all levels' corners first, prefetched, so that their memory reads overlap
            for (int l = 0; l < n_levels; ++l) {
                corners(x + 3 * b, res[l], dense[l] != 0, table_size, features, c[l]);
                prefetch(params[l], c[l], features);
            }
            float* o = out + b * static_cast<int64_t>(n_levels) * features;
            for (int l = 0; l < n_levels; ++l) {
                const float* data = params[l];
                for (int f = 0; f < features; ++f) {
                    float acc = 0.0f;
                    for (int k = 0; k < 8; ++k) acc += c[l].weight[k] * data[c[l].index[k] + f * c[l].feature_stride];
                    o[l * features + f] = acc;
                }
            }
        }
    }
}

// grad_params[l] (same layout as params[l], zeroed) accumulate d loss / d parameters. Levels write
// disjoint memory, so threads split the levels and need no atomics; grad_x, when not null,
// receives d loss / d x (n, 3) in a second pass over the points.
void hashgrid_backward(const float* x, int64_t n, int n_levels, const int* res, const int* dense,
                       const float* const* params, int64_t table_size, int features, const float* grad_out,
                       float* const* grad_params, float* grad_x, int n_threads) {
    const int64_t row = static_cast<int64_t>(n_levels) * features;
#pragma omp parallel for num_threads(n_threads) schedule(dynamic, 1)
    for (int l = 0; l < n_levels; ++l) {
        Corners ring[kLookahead];  // corners of the next points, prefetched while this one is added
        float* grad = grad_params[l];
        for (int64_t b = 0; b < n + kLookahead; ++b) {
            Corners& c = ring[b % kLookahead];
            if (b >= kLookahead) {
                const int64_t p = b - kLookahead;
                for (int f = 0; f < features; ++f) {
                    const float gf = grad_out[p * row + l * features + f];
                    for (int k = 0; k < 8; ++k) grad[c.index[k] + f * c.feature_stride] += c.weight[k] * gf;
                }
            }
            if (b < n) {
                corners(x + 3 * b, res[l], dense[l] != 0, table_size, features, c);
                prefetch(grad, c, features);
            }
        }
    }
    if (grad_x == nullptr) return;
#pragma omp parallel for num_threads(n_threads) schedule(static)
    for (int64_t b = 0; b < n; ++b) {
        Corners c;
        float gx[3] = {0.0f, 0.0f, 0.0f};
        for (int l = 0; l < n_levels; ++l) {
            corners(x + 3 * b, res[l], dense[l] != 0, table_size, features, c);
            const float* data = params[l];
            for (int f = 0; f < features; ++f) {
                const float gf = grad_out[b * row + l * features + f] * static_cast<float>(res[l]);
                for (int k = 0; k < 8; ++k) {
                    const float v = data[c.index[k] + f * c.feature_stride] * gf;
                    gx[0] += v * c.dweight[k][0];
                    gx[1] += v * c.dweight[k][1];
                    gx[2] += v * c.dweight[k][2];
                }
            }
        }
        grad_x[3 * b] = gx[0];
        grad_x[3 * b + 1] = gx[1];
        grad_x[3 * b + 2] = gx[2];
    }
}

}  // extern "C"
