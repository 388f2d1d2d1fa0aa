// The multi-resolution hash-grid encoding (HashGridEncoding) as two torch custom operators on the
// CPU, parallel over points with OpenMP:
//   open3d_pnerf::hashgrid_encode(x, params, resolutions, dense, table_size, features, known) -> out
//   open3d_pnerf::hashgrid_encode_backward(grad_out, x, params, ...) -> (grad_x, grad_params)
// native.py builds this file with torch.utils.cpp_extension, pairs the two in an autograd formula
// and registers their shapes for tracing; HashGridEncoding's pure-PyTorch path is the reference
// the tests hold it against.
//
// Levels: level l has res[l] cells per axis over [0, 1]^3 (vertex i at i / res[l]). A dense level
// (dense[l] = 1) is a volume of (res + 1)^3 vertices stored as grid_sample's (F, D, H, W) =
// (F, z, y, x); a hashed level is `table_size` rows of F features, row = hash(corner) &
// (table_size - 1) with Instant-NGP's primes (1, 2654435761, 805459861): the low bits of the
// 32-bit products equal those of PyTorch's 64-bit ones. params: the dense levels' volumes, then
// one table holding every hashed level's rows, level after level.
// Points x (n, 3): a coordinate outside [0, 1] is clamped onto the box (no gradient along it); a
// point with a NaN or infinite coordinate encodes to 0 and gets no gradient.
// Output: out[b, l * F + f], levels in order. known (m, L * F), optional: the encoding of x's last
// m rows, computed before; copied instead of recomputed (the backward covers every row).

#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/copy.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/empty_like.h>
#include <ATen/ops/from_blob.h>
#include <ATen/ops/narrow.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <optional>
#include <tuple>
#include <utility>
#include <vector>

namespace {

constexpr int kMaxLevels = 32;  // checked below; native.MAX_LEVELS
constexpr int kLookahead = 8;   // points whose corners the backward prefetches ahead

template <typename T>
struct Corners {
    int64_t index[8];  // element offset of feature 0 of each corner
    T weight[8];
    T frac[3];  // position in the cell along x, y, z
    T free[3];  // 1 along an axis where the point lies in [0, 1], 0 where it was clamped onto the box
    int64_t feature_stride;
};

// Whether all three coordinates of p are finite (one test: a sum with a NaN or an inf is not).
template <typename T>
inline bool finite(const T* p) {
    return std::isfinite(p[0] + p[1] + p[2]);
}

// The cell corners of a finite point p on one level.
template <typename T>
inline void corners(const T* p, int res, bool dense, int64_t table_size, int features, Corners<T>& c) {
    int64_t base[3];
    for (int a = 0; a < 3; ++a) {
        const T clamped = p[a] < T(0) ? T(0) : (p[a] > T(1) ? T(1) : p[a]);
        c.free[a] = clamped == p[a] ? T(1) : T(0);
        const T pos = clamped * static_cast<T>(res);
        T f = std::floor(pos);
        if (f > static_cast<T>(res - 1)) f = static_cast<T>(res - 1);  // x = 1 uses the last cell
        base[a] = static_cast<int64_t>(f);
        c.frac[a] = pos - f;
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
        const T wx = dx ? c.frac[0] : T(1) - c.frac[0];
        const T wy = dy ? c.frac[1] : T(1) - c.frac[1];
        const T wz = dz ? c.frac[2] : T(1) - c.frac[2];
        c.weight[k] = wz * wy * wx;
    }
}

// d weight[k] / d frac along x, y, z of corner k (0 along a clamped axis).
template <typename T>
inline void weight_gradient(const Corners<T>& c, int k, T out[3]) {
    const int dx = k & 1, dy = (k >> 1) & 1, dz = (k >> 2) & 1;
    const T wx = dx ? c.frac[0] : T(1) - c.frac[0];
    const T wy = dy ? c.frac[1] : T(1) - c.frac[1];
    const T wz = dz ? c.frac[2] : T(1) - c.frac[2];
    const T sx = dx ? T(1) : T(-1), sy = dy ? T(1) : T(-1), sz = dz ? T(1) : T(-1);
    out[0] = wz * wy * sx * c.free[0];
    out[1] = wz * sy * wx * c.free[1];
    out[2] = sz * wy * wx * c.free[2];
}

template <typename T>
inline void prefetch(const T* data, const Corners<T>& c, int features) {
    for (int k = 0; k < 8; ++k) {
        __builtin_prefetch(data + c.index[k]);
        if (c.feature_stride != 1)  // dense levels keep each feature in its own volume
            for (int f = 1; f < features; ++f) __builtin_prefetch(data + c.index[k] + f * c.feature_stride);
    }
}

struct Levels {
    std::vector<int> res, dense;
    int64_t table_size;
    int features;
    int n() const { return static_cast<int>(res.size()); }
    int64_t size(int l) const {  // elements of level l's parameters
        const int64_t v = res[l] + 1;
        return dense[l] ? features * v * v * v : table_size * features;
    }
};

// Each level's data pointer: a dense level's volume, or a hashed level's rows of the table.
template <typename T>
std::vector<T*> level_pointers(const std::vector<at::Tensor>& params, const Levels& lv) {
    std::vector<T*> out;
    int n_dense = 0;
    for (int d : lv.dense) n_dense += d;
    for (int l = 0; l < n_dense; ++l) out.push_back(params[l].data_ptr<T>());
    for (int l = n_dense; l < lv.n(); ++l)
        out.push_back(params[n_dense].data_ptr<T>() + (l - n_dense) * lv.table_size * lv.features);
    return out;
}

Levels check(const at::Tensor& x, const std::vector<at::Tensor>& params, at::IntArrayRef resolutions,
             at::IntArrayRef dense, int64_t table_size, int64_t features) {
    TORCH_CHECK(x.device().is_cpu() && x.dim() == 2 && x.size(1) == 3, "hashgrid_encode: x must be a CPU (n, 3) tensor");
    TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble,
                "hashgrid_encode: x must be float32 or float64");
    TORCH_CHECK(resolutions.size() == dense.size() && !resolutions.empty() && resolutions.size() <= kMaxLevels,
                "hashgrid_encode: 1 to ", kMaxLevels, " levels, one dense flag each");
    TORCH_CHECK(table_size > 0 && (table_size & (table_size - 1)) == 0 && features >= 1,
                "hashgrid_encode: table_size must be a power of 2 and features >= 1");
    Levels lv{{}, {}, table_size, static_cast<int>(features)};
    int n_dense = 0, n_hashed = 0;
    for (size_t l = 0; l < resolutions.size(); ++l) {
        TORCH_CHECK(resolutions[l] >= 1, "hashgrid_encode: resolutions must be >= 1");
        TORCH_CHECK(!dense[l] || n_hashed == 0, "hashgrid_encode: the dense levels come first");
        lv.res.push_back(static_cast<int>(resolutions[l]));
        lv.dense.push_back(dense[l] != 0);
        ++(dense[l] ? n_dense : n_hashed);
    }
    TORCH_CHECK(static_cast<int>(params.size()) == n_dense + (n_hashed > 0), "hashgrid_encode: expected ", n_dense,
                " dense volumes", n_hashed ? " and the table" : "", ", got ", params.size(), " tensors");
    for (int l = 0; l < n_dense; ++l) {
        const int64_t v = resolutions[l] + 1;
        TORCH_CHECK(params[l].sizes() == at::IntArrayRef({1, features, v, v, v}), "hashgrid_encode: dense level ", l,
                    " must be (1, ", features, ", ", v, ", ", v, ", ", v, "), got ", params[l].sizes());
    }
    if (n_hashed)
        TORCH_CHECK(params[n_dense].sizes() == at::IntArrayRef({n_hashed * table_size, features}),
                    "hashgrid_encode: the table must be (", n_hashed * table_size, ", ", features, "), got ",
                    params[n_dense].sizes());
    for (const auto& p : params)
        TORCH_CHECK(p.device().is_cpu() && p.scalar_type() == x.scalar_type(),
                    "hashgrid_encode: parameters must be CPU tensors of x's dtype");
    return lv;
}

template <typename T>
void forward_kernel(const T* x, int64_t n, const Levels& lv, const std::vector<T*>& params, T* out) {
    const int features = lv.features, n_levels = lv.n();
    const int64_t row = static_cast<int64_t>(n_levels) * features;
#pragma omp parallel num_threads(at::get_num_threads())
    {
        Corners<T> c[kMaxLevels];
#pragma omp for schedule(static)
        for (int64_t b = 0; b < n; ++b) {
            T* o = out + b * row;
            if (!finite(x + 3 * b)) {
                std::fill(o, o + row, T(0));
                continue;
            }
            // all levels' corners first, prefetched, so that their memory reads overlap
            for (int l = 0; l < n_levels; ++l) {
                corners(x + 3 * b, lv.res[l], lv.dense[l] != 0, lv.table_size, features, c[l]);
                prefetch<T>(params[l], c[l], features);
            }
            for (int l = 0; l < n_levels; ++l) {
                const T* data = params[l];
                for (int f = 0; f < features; ++f) {
                    T acc = T(0);
                    for (int k = 0; k < 8; ++k) acc += c[l].weight[k] * data[c[l].index[k] + f * c[l].feature_stride];
                    o[l * features + f] = acc;
                }
            }
        }
    }
}

// grad_params[l] (same layout as params[l], zeroed here) accumulate d loss / d parameters, point
// after point in x's order. Levels write disjoint memory, so threads split the levels and need no
// atomics; grad_x, when not null, receives d loss / d x (n, 3) in a second pass over the points.
template <typename T>
void backward_kernel(const T* x, int64_t n, const Levels& lv, const std::vector<T*>& params, const T* grad_out,
                     const std::vector<T*>& grad_params, T* grad_x) {
    const int features = lv.features, n_levels = lv.n();
    const int64_t row = static_cast<int64_t>(n_levels) * features;
#pragma omp parallel for num_threads(at::get_num_threads()) schedule(dynamic, 1)
    for (int l = 0; l < n_levels; ++l) {
        Corners<T> ring[kLookahead];  // corners of the next points, prefetched while this one is added
        bool ok[kLookahead];
        T* grad = grad_params[l];
        std::memset(grad, 0, lv.size(l) * sizeof(T));
        for (int64_t b = 0; b < n + kLookahead; ++b) {
            const int slot = static_cast<int>(b % kLookahead);
            if (b >= kLookahead && ok[slot]) {
                const Corners<T>& c = ring[slot];
                const int64_t p = b - kLookahead;
                for (int f = 0; f < features; ++f) {
                    const T gf = grad_out[p * row + l * features + f];
                    for (int k = 0; k < 8; ++k) grad[c.index[k] + f * c.feature_stride] += c.weight[k] * gf;
                }
            }
            if (b < n) {
                ok[slot] = finite(x + 3 * b);
                if (ok[slot]) {
                    corners(x + 3 * b, lv.res[l], lv.dense[l] != 0, lv.table_size, features, ring[slot]);
                    prefetch<T>(grad, ring[slot], features);
                }
            }
        }
    }
    if (grad_x == nullptr) return;
#pragma omp parallel for num_threads(at::get_num_threads()) schedule(static)
    for (int64_t b = 0; b < n; ++b) {
        Corners<T> c;
        T gx[3] = {T(0), T(0), T(0)};
        for (int l = 0; l < n_levels && finite(x + 3 * b); ++l) {
            corners(x + 3 * b, lv.res[l], lv.dense[l] != 0, lv.table_size, features, c);
            const T* data = params[l];
            for (int f = 0; f < features; ++f) {
                const T gf = grad_out[b * row + l * features + f] * static_cast<T>(lv.res[l]);
                for (int k = 0; k < 8; ++k) {
                    const T v = data[c.index[k] + f * c.feature_stride] * gf;
                    T dw[3];
                    weight_gradient(c, k, dw);
                    gx[0] += v * dw[0];
                    gx[1] += v * dw[1];
                    gx[2] += v * dw[2];
                }
            }
        }
        grad_x[3 * b] = gx[0];
        grad_x[3 * b + 1] = gx[1];
        grad_x[3 * b + 2] = gx[2];
    }
}

// Memory of the parameter gradients. The table's gradient is tens of megabytes, written every
// training step; memory fresh from the system costs more than the kernel (page faults, cold
// caches), so when torch frees a gradient tensor its memory comes back here and the next gradient
// of that size reuses it. Torch decides when a tensor dies: the pool only keeps its freed memory.
class GradientMemory {
  public:
    static GradientMemory& instance() {
        static GradientMemory* memory = new GradientMemory;  // never destroyed: tensors may outlive statics
        return *memory;
    }

    at::Tensor empty_like(const at::Tensor& like) {
        const size_t bytes = like.numel() * like.element_size();
        void* data = take(bytes);
        return at::from_blob(data, like.sizes(), [bytes](void* p) { instance().give_back(p, bytes); }, like.options());
    }

  private:
    static constexpr size_t kKeep = 8;  // freed blocks kept for reuse; more are returned to the system

    void* take(size_t bytes) {
        {
            std::lock_guard<std::mutex> lock(mutex_);
            for (size_t i = 0; i < free_.size(); ++i)
                if (free_[i].first == bytes) {
                    void* data = free_[i].second;
                    free_.erase(free_.begin() + static_cast<std::ptrdiff_t>(i));
                    return data;
                }
        }
        void* data = std::aligned_alloc(64, (bytes + 63) / 64 * 64);
        TORCH_CHECK(data != nullptr, "hashgrid_encode_backward: out of memory for ", bytes, " bytes of gradient");
        return data;
    }

    void give_back(void* data, size_t bytes) {
        std::lock_guard<std::mutex> lock(mutex_);
        if (free_.size() < kKeep)
            free_.emplace_back(bytes, data);
        else
            std::free(data);
    }

    std::mutex mutex_;
    std::vector<std::pair<size_t, void*>> free_;
};

std::vector<at::Tensor> contiguous(at::TensorList tensors) {
    std::vector<at::Tensor> out;
    for (const auto& t : tensors) out.push_back(t.contiguous());
    return out;
}

template <typename T>
void encode(const at::Tensor& x, int64_t n, const Levels& lv, const std::vector<at::Tensor>& params, at::Tensor& out) {
    forward_kernel<T>(x.data_ptr<T>(), n, lv, level_pointers<T>(params, lv), out.data_ptr<T>());
}

at::Tensor hashgrid_encode(const at::Tensor& x_in, at::TensorList params_in, at::IntArrayRef resolutions,
                           at::IntArrayRef dense, int64_t table_size, int64_t features,
                           const std::optional<at::Tensor>& known) {
    const at::Tensor x = x_in.contiguous();
    const std::vector<at::Tensor> params = contiguous(params_in);
    const Levels lv = check(x, params, resolutions, dense, table_size, features);
    const int64_t width = lv.n() * features;
    at::Tensor out = at::empty({x.size(0), width}, x.options());
    const int64_t m = known.has_value() ? known->size(0) : 0;
    if (known.has_value()) {
        TORCH_CHECK(known->dim() == 2 && m <= x.size(0) && known->size(1) == width &&
                        known->scalar_type() == x.scalar_type() && known->device().is_cpu(),
                    "hashgrid_encode: known must be (m <= ", x.size(0), ", ", width, ") of x's dtype, got ",
                    known->sizes());
        out.narrow(0, x.size(0) - m, m).copy_(*known);
    }
    if (x.scalar_type() == at::kFloat)
        encode<float>(x, x.size(0) - m, lv, params, out);
    else
        encode<double>(x, x.size(0) - m, lv, params, out);
    return out;
}

std::tuple<at::Tensor, std::vector<at::Tensor>> hashgrid_encode_backward(
    const at::Tensor& grad_out_in, const at::Tensor& x_in, at::TensorList params_in, at::IntArrayRef resolutions,
    at::IntArrayRef dense, int64_t table_size, int64_t features, bool x_needs_grad) {
    const at::Tensor x = x_in.contiguous(), grad_out = grad_out_in.contiguous();
    const std::vector<at::Tensor> params = contiguous(params_in);
    const Levels lv = check(x, params, resolutions, dense, table_size, features);
    TORCH_CHECK(grad_out.sizes() == at::IntArrayRef({x.size(0), lv.n() * features}) &&
                    grad_out.scalar_type() == x.scalar_type(),
                "hashgrid_encode_backward: grad_out must be (n, levels * features) of x's dtype");
    std::vector<at::Tensor> grads;
    for (const auto& p : params) grads.push_back(GradientMemory::instance().empty_like(p));
    at::Tensor grad_x = x_needs_grad ? at::empty_like(x) : at::zeros({0, 3}, x.options());
    if (x.scalar_type() == at::kFloat)
        backward_kernel<float>(x.data_ptr<float>(), x.size(0), lv, level_pointers<float>(params, lv),
                               grad_out.data_ptr<float>(), level_pointers<float>(grads, lv),
                               x_needs_grad ? grad_x.data_ptr<float>() : nullptr);
    else
        backward_kernel<double>(x.data_ptr<double>(), x.size(0), lv, level_pointers<double>(params, lv),
                                grad_out.data_ptr<double>(), level_pointers<double>(grads, lv),
                                x_needs_grad ? grad_x.data_ptr<double>() : nullptr);
    return {grad_x, grads};
}

}  // namespace

TORCH_LIBRARY(open3d_pnerf, m) {
    m.def("hashgrid_encode(Tensor x, Tensor[] params, int[] resolutions, int[] dense, int table_size, int features, "
          "Tensor? known=None) -> Tensor");
    m.def("hashgrid_encode_backward(Tensor grad_out, Tensor x, Tensor[] params, int[] resolutions, int[] dense, "
          "int table_size, int features, bool x_needs_grad) -> (Tensor, Tensor[])");
}

TORCH_LIBRARY_IMPL(open3d_pnerf, CPU, m) {
    m.impl("hashgrid_encode", &hashgrid_encode);
    m.impl("hashgrid_encode_backward", &hashgrid_encode_backward);
}
