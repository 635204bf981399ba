// Tiled Gaussian compositing on the CPU: forward and hand-written backward.
//
// Same contract as renderworld/splat/tiled.py (its pure-torch twin and test oracle): pixel
// centres at (i + 0.5, j + 0.5); alpha = min(0.99, opacity * exp(-power)), power clamped >= 0;
// pairs with alpha < 1/255 skipped; a pixel stops before the Gaussian that would bring its
// transmittance to <= 1e-4. Tiles are independent and run in parallel (at::parallel_for);
// backward writes one gradient row per tile intersection, so no two threads share memory.
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace {

constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kAlphaMax = 0.99;
constexpr double kTMin = 1e-4;

struct Geometry {
  int64_t tiles_x, tiles_y, tile, width, height, num_g, dim;
};

// Pixels of tile (tx, ty) whose centres lie in the Gaussian's alpha >= 1/255 box: [c0, c1] x
// [r0, r1] in tile-local coordinates (empty when c0 > c1 or r0 > r1).
template <typename T>
inline void pixel_rect(const Geometry& g, int64_t tx, int64_t ty, T u, T v, const T* ext,
                       int64_t& c0, int64_t& c1, int64_t& r0, int64_t& r1) {
  const T x0 = T(tx * g.tile), y0 = T(ty * g.tile);
  const T x1 = T(std::min((tx + 1) * g.tile, g.width) - 1);
  const T y1 = T(std::min((ty + 1) * g.tile, g.height) - 1);
  const T lo_x = std::max(x0, std::ceil(u - ext[0] - T(0.5)));
  const T hi_x = std::min(x1, std::floor(u + ext[0] - T(0.5)));
  const T lo_y = std::max(y0, std::ceil(v - ext[1] - T(0.5)));
  const T hi_y = std::min(y1, std::floor(v + ext[1] - T(0.5)));
  c0 = static_cast<int64_t>(lo_x) - tx * g.tile;
  c1 = static_cast<int64_t>(hi_x) - tx * g.tile;
  r0 = static_cast<int64_t>(lo_y) - ty * g.tile;
  r1 = static_cast<int64_t>(hi_y) - ty * g.tile;
}

// exp(x) for x <= 0, branch-free so that loops calling it vectorize (x below -80 is treated as
// -80: the result, ~1e-35, is far under 1/255 anyway). Cody–Waite reduction x = n·ln2 + r,
// |r| <= ln2/2, then a Taylor polynomial: about 1 ulp in float, a few ulp in double.
template <typename T>
struct ExpConsts;
template <>
struct ExpConsts<float> {
  using Int = int32_t;
  static constexpr int kBias = 127, kMant = 23, kDegree = 7;
  static constexpr float kLn2Hi = 0.693359375f, kLn2Lo = -2.12194440e-4f;
};
template <>
struct ExpConsts<double> {
  using Int = int64_t;
  static constexpr int kBias = 1023, kMant = 52, kDegree = 13;
  static constexpr double kLn2Hi = 6.93147180369123816490e-01;
  static constexpr double kLn2Lo = 1.90821492927058770002e-10;
};

template <typename T>
inline T exp_nonpositive(T x) {
  using C = ExpConsts<T>;
  x = std::max(x, T(-80));
  const T n = std::floor(x * T(1.44269504088896340736) + T(0.5));
  const T r = (x - n * C::kLn2Hi) - n * C::kLn2Lo;
  // Horner form of the Taylor series, written out so that the loop calling this vectorizes.
  T poly = T(1);
  if constexpr (C::kDegree >= 13) poly = T(1) + poly * r * T(1.0 / 13);
  if constexpr (C::kDegree >= 12) poly = T(1) + poly * r * T(1.0 / 12);
  if constexpr (C::kDegree >= 11) poly = T(1) + poly * r * T(1.0 / 11);
  if constexpr (C::kDegree >= 10) poly = T(1) + poly * r * T(1.0 / 10);
  if constexpr (C::kDegree >= 9) poly = T(1) + poly * r * T(1.0 / 9);
  if constexpr (C::kDegree >= 8) poly = T(1) + poly * r * T(1.0 / 8);
  poly = T(1) + poly * r * T(1.0 / 7);
  poly = T(1) + poly * r * T(1.0 / 6);
  poly = T(1) + poly * r * T(1.0 / 5);
  poly = T(1) + poly * r * T(1.0 / 4);
  poly = T(1) + poly * r * T(1.0 / 3);
  poly = T(1) + poly * r * T(1.0 / 2);
  poly = T(1) + poly * r;
  // 2^n from its exponent bits (n in [-116, 0]; via int32 so the conversion vectorizes).
  const auto bits = static_cast<typename C::Int>(static_cast<int32_t>(n) + C::kBias) << C::kMant;
  T scale;
  static_assert(sizeof(bits) == sizeof(T), "exponent bits must match the float width");
  std::memcpy(&scale, &bits, sizeof(T));
  return poly * scale;
}

// One row of a tile against one Gaussian: pixel x offsets, power and unclamped alpha
// op * exp(-power) for columns [c0, c0 + n) (tile-local), vectorized over pixels.
template <typename T>
inline void eval_row(T u, T dy, const T* con, T op, T x0, int64_t c0, int n, T* dxs, T* pws,
                     T* als) {
  const T dx0 = x0 + T(c0) + T(0.5) - u;
  const T ca = T(0.5) * con[0], cb = con[1], cyy = T(0.5) * con[2] * dy * dy;
#pragma omp simd
  for (int k = 0; k < n; ++k) {  // int index: int32 -> float conversion vectorizes on AVX2
    const T dx = dx0 + T(k);
    const T pw = std::max(ca * dx * dx + cyy + cb * dx * dy, T(0));
    dxs[k] = dx;
    pws[k] = pw;
    als[k] = op * exp_nonpositive(-pw);
  }
}

template <typename T>
void forward_impl(const Geometry& g, const T* means2d, const T* conics, const T* extents,
                  const T* depths, const int64_t* pair_gauss, const T* opac, const T* feats,
                  const int64_t* ids, const int64_t* offs, int64_t num_tiles, T* out, T* t_final,
                  int64_t* last) {
  const int64_t P = g.tile * g.tile, K = g.dim + 2, tpc = g.tiles_x * g.tiles_y;
  at::parallel_for(0, num_tiles, 1, [&](int64_t t0, int64_t t1) {
    std::vector<T> acc(P * K), trans(P), dxs(g.tile), pws(g.tile), als(g.tile);
    std::vector<int64_t> lst(P);
    std::vector<char> done(P);
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t cam = t / tpc, tl = t % tpc, ty = tl / g.tiles_x, tx = tl % g.tiles_x;
      const int64_t start = offs[t], end = offs[t + 1];
      int64_t alive = 0;
      for (int64_t p = 0; p < P; ++p) {
        const int64_t col = tx * g.tile + p % g.tile, row = ty * g.tile + p / g.tile;
        done[p] = (col >= g.width || row >= g.height);
        alive += !done[p];
        trans[p] = T(1);
        lst[p] = start;
      }
      std::fill(acc.begin(), acc.end(), T(0));
      const T x0 = T(tx * g.tile);
      for (int64_t j = start; j < end && alive > 0; ++j) {
        const int64_t gid = ids[j], n = pair_gauss[gid];
        const T u = means2d[2 * gid], v = means2d[2 * gid + 1], op = opac[n], z = depths[gid];
        const T* con = conics + 3 * gid;
        const T* f = feats + n * g.dim;
        int64_t c0, c1, r0, r1;
        pixel_rect(g, tx, ty, u, v, extents + 2 * gid, c0, c1, r0, r1);
        for (int64_t r = r0; r <= r1; ++r) {
          const T dy = T(ty * g.tile + r) + T(0.5) - v;
          eval_row(u, dy, con, op, x0, c0, static_cast<int>(c1 - c0 + 1), dxs.data(), pws.data(),
                   als.data());
          for (int64_t k = 0; k <= c1 - c0; ++k) {
            const int64_t p = r * g.tile + c0 + k;
            if (done[p] || als[k] < T(kAlphaMin)) continue;
            const T alpha = std::min(als[k], T(kAlphaMax));
            const T next = trans[p] * (T(1) - alpha);
            if (next <= T(kTMin)) {
              done[p] = 1;
              --alive;
              continue;
            }
            const T w = alpha * trans[p];
            T* a = acc.data() + p * K;
            for (int64_t d = 0; d < g.dim; ++d) a[d] += w * f[d];
            a[g.dim] += w * z;
            trans[p] = next;
            lst[p] = j + 1;
          }
        }
      }
      for (int64_t p = 0; p < P; ++p) {
        const int64_t col = tx * g.tile + p % g.tile, row = ty * g.tile + p / g.tile;
        if (col >= g.width || row >= g.height) continue;
        const int64_t pix = (cam * g.height + row) * g.width + col;
        T* o = out + pix * K;
        for (int64_t d = 0; d <= g.dim; ++d) o[d] = acc[p * K + d];
        o[g.dim + 1] = T(1) - trans[p];
        t_final[pix] = trans[p];
        last[pix] = lst[p];
      }
    }
  });
}

// grad row layout per intersection: [u, v, conic a, b, c, opacity, depth, features...].
template <typename T>
void backward_impl(const Geometry& g, const T* means2d, const T* conics, const T* extents,
                   const T* depths, const int64_t* pair_gauss, const T* opac, const T* feats,
                   const int64_t* ids, const int64_t* offs, int64_t num_tiles, const T* gout,
                   const T* t_final, const int64_t* last, T* grows) {
  const int64_t P = g.tile * g.tile, K = g.dim + 2, R = 7 + g.dim, tpc = g.tiles_x * g.tiles_y;
  at::parallel_for(0, num_tiles, 1, [&](int64_t t0, int64_t t1) {
    std::vector<T> trans(P), tfin(P), suffix(P), gdep(P), galpha(P), gfeat(P * g.dim);
    std::vector<T> dxs(g.tile), pws(g.tile), als(g.tile), row(R);
    std::vector<int64_t> lst(P);
    for (int64_t t = t0; t < t1; ++t) {
      const int64_t cam = t / tpc, tl = t % tpc, ty = tl / g.tiles_x, tx = tl % g.tiles_x;
      const int64_t start = offs[t];
      int64_t jmax = start;
      for (int64_t p = 0; p < P; ++p) {
        const int64_t col = tx * g.tile + p % g.tile, rw = ty * g.tile + p / g.tile;
        if (col >= g.width || rw >= g.height) {
          lst[p] = start;
          continue;
        }
        const int64_t pix = (cam * g.height + rw) * g.width + col;
        lst[p] = last[pix];
        jmax = std::max(jmax, lst[p]);
        trans[p] = tfin[p] = t_final[pix];
        suffix[p] = T(0);
        const T* go = gout + pix * K;
        for (int64_t d = 0; d < g.dim; ++d) gfeat[p * g.dim + d] = go[d];
        gdep[p] = go[g.dim];
        galpha[p] = go[g.dim + 1];
      }
      const T x0 = T(tx * g.tile);
      for (int64_t j = jmax - 1; j >= start; --j) {
        const int64_t gid = ids[j], n = pair_gauss[gid];
        const T u = means2d[2 * gid], v = means2d[2 * gid + 1], op = opac[n], z = depths[gid];
        const T* con = conics + 3 * gid;
        const T* f = feats + n * g.dim;
        int64_t c0, c1, r0, r1;
        pixel_rect(g, tx, ty, u, v, extents + 2 * gid, c0, c1, r0, r1);
        std::fill(row.begin(), row.end(), T(0));
        for (int64_t r = r0; r <= r1; ++r) {
          const T dy = T(ty * g.tile + r) + T(0.5) - v;
          eval_row(u, dy, con, op, x0, c0, static_cast<int>(c1 - c0 + 1), dxs.data(), pws.data(),
                   als.data());
          for (int64_t k = 0; k <= c1 - c0; ++k) {
            const int64_t p = r * g.tile + c0 + k;
            if (j >= lst[p] || als[k] < T(kAlphaMin)) continue;
            const bool clamped = als[k] > T(kAlphaMax);
            const T alpha = clamped ? T(kAlphaMax) : als[k];
            const T ra = T(1) / (T(1) - alpha);
            trans[p] *= ra;  // transmittance in front of Gaussian j
            const T w = alpha * trans[p];
            const T* gf = gfeat.data() + p * g.dim;
            T dot = gdep[p] * z;
            for (int64_t d = 0; d < g.dim; ++d) {
              row[7 + d] += w * gf[d];
              dot += gf[d] * f[d];
            }
            row[6] += w * gdep[p];
            const T dalpha = trans[p] * dot - suffix[p] * ra + galpha[p] * tfin[p] * ra;
            suffix[p] += w * dot;
            if (clamped) continue;
            row[5] += dalpha * (alpha / op);
            if (pws[k] <= T(0)) continue;
            const T dpow = -dalpha * alpha;
            const T dx = dxs[k];
            row[0] -= dpow * (con[0] * dx + con[1] * dy);
            row[1] -= dpow * (con[1] * dx + con[2] * dy);
            row[2] += dpow * T(0.5) * dx * dx;
            row[3] += dpow * dx * dy;
            row[4] += dpow * T(0.5) * dy * dy;
          }
        }
        std::copy(row.begin(), row.end(), grows + j * R);
      }
    }
  });
}

Geometry make_geometry(int64_t tiles_x, int64_t tiles_y, int64_t tile, int64_t width,
                       int64_t height, const torch::Tensor& opac, const torch::Tensor& feats) {
  return Geometry{tiles_x, tiles_y, tile, width, height, opac.size(0), feats.size(1)};
}

}  // namespace

std::vector<torch::Tensor> splat_forward(torch::Tensor means2d, torch::Tensor conics,
                                         torch::Tensor extents, torch::Tensor depths,
                                         torch::Tensor pair_gauss, torch::Tensor opac,
                                         torch::Tensor feats, torch::Tensor ids,
                                         torch::Tensor offs, int64_t num_cams, int64_t tiles_x,
                                         int64_t tiles_y, int64_t tile, int64_t width,
                                         int64_t height) {
  const Geometry g = make_geometry(tiles_x, tiles_y, tile, width, height, opac, feats);
  auto opts = means2d.options();
  auto out = torch::empty({num_cams, height, width, g.dim + 2}, opts);  // every pixel written
  auto t_final = torch::empty({num_cams, height, width}, opts);
  auto last = torch::empty({num_cams, height, width}, opts.dtype(torch::kInt64));
  const int64_t num_tiles = offs.size(0) - 1;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "splat_forward", [&] {
    forward_impl<scalar_t>(g, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                           extents.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(),
                           pair_gauss.data_ptr<int64_t>(),
                           opac.data_ptr<scalar_t>(), feats.data_ptr<scalar_t>(),
                           ids.data_ptr<int64_t>(),
                           offs.data_ptr<int64_t>(), num_tiles, out.data_ptr<scalar_t>(),
                           t_final.data_ptr<scalar_t>(), last.data_ptr<int64_t>());
  });
  return {out, t_final, last};
}

torch::Tensor splat_backward(torch::Tensor means2d, torch::Tensor conics,
                             torch::Tensor extents, torch::Tensor depths,
                             torch::Tensor pair_gauss, torch::Tensor opac, torch::Tensor feats,
                             torch::Tensor ids,
                             torch::Tensor offs, int64_t tiles_x, int64_t tiles_y, int64_t tile,
                             int64_t width, int64_t height, torch::Tensor gout,
                             torch::Tensor t_final, torch::Tensor last) {
  const Geometry g = make_geometry(tiles_x, tiles_y, tile, width, height, opac, feats);
  auto grows = torch::zeros({ids.size(0), 7 + g.dim}, means2d.options());
  const int64_t num_tiles = offs.size(0) - 1;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "splat_backward", [&] {
    backward_impl<scalar_t>(g, means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                           extents.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(),
                           pair_gauss.data_ptr<int64_t>(),
                            opac.data_ptr<scalar_t>(), feats.data_ptr<scalar_t>(),
                            ids.data_ptr<int64_t>(),
                            offs.data_ptr<int64_t>(), num_tiles, gout.data_ptr<scalar_t>(),
                            t_final.data_ptr<scalar_t>(), last.data_ptr<int64_t>(),
                            grows.data_ptr<scalar_t>());
  });
  return grows;
}
