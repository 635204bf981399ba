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

template <typename T>
inline bool eval_alpha(T u, T v, const T* con, T op, T log_thr, T px, T py, T& dx, T& dy, T& power,
                       T& alpha, bool& clamped) {
  dx = px - u;
  dy = py - v;
  power = T(0.5) * (con[0] * dx * dx + con[2] * dy * dy) + con[1] * dx * dy;
  if (power < T(0)) power = T(0);
  if (power > log_thr) return false;  // op * exp(-power) < 1/255 for sure: skip the exp
  T a = op * std::exp(-power);
  clamped = a > T(kAlphaMax);
  alpha = clamped ? T(kAlphaMax) : a;
  return alpha >= T(kAlphaMin);
}

template <typename T>
void forward_impl(const Geometry& g, const T* means2d, const T* conics, const T* extents,
                  const T* depths, const int64_t* pair_gauss, const T* opac, const T* feats,
                  const int64_t* ids, const int64_t* offs,
                  int64_t num_tiles, T* out, T* t_final, int64_t* last) {
  const int64_t P = g.tile * g.tile, K = g.dim + 2, tpc = g.tiles_x * g.tiles_y;
  at::parallel_for(0, num_tiles, 1, [&](int64_t t0, int64_t t1) {
    std::vector<T> acc(P * K), trans(P);
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
      for (int64_t j = start; j < end && alive > 0; ++j) {
        const int64_t gid = ids[j], n = pair_gauss[gid];
        const T u = means2d[2 * gid], v = means2d[2 * gid + 1], op = opac[n], z = depths[gid];
        const T* con = conics + 3 * gid;
        const T* f = feats + n * g.dim;
        const T log_thr = std::log(op * T(255)) + T(1e-6);
        int64_t c0, c1, r0, r1;
        pixel_rect(g, tx, ty, u, v, extents + 2 * gid, c0, c1, r0, r1);
        for (int64_t r = r0; r <= r1; ++r)
        for (int64_t cc = c0; cc <= c1; ++cc) {
          const int64_t p = r * g.tile + cc;
          if (done[p]) continue;
          const T px = T(tx * g.tile + cc) + T(0.5);
          const T py = T(ty * g.tile + r) + T(0.5);
          T dx, dy, power, alpha;
          bool clamped;
          if (!eval_alpha(u, v, con, op, log_thr, px, py, dx, dy, power, alpha, clamped)) continue;
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
                   const int64_t* ids, const int64_t* offs,
                   int64_t num_tiles, const T* gout, const T* t_final, const int64_t* last,
                   T* grows) {
  const int64_t P = g.tile * g.tile, K = g.dim + 2, R = 7 + g.dim, tpc = g.tiles_x * g.tiles_y;
  at::parallel_for(0, num_tiles, 1, [&](int64_t t0, int64_t t1) {
    std::vector<T> trans(P), tfin(P), suffix(P), gdep(P), galpha(P), gfeat(P * g.dim);
    std::vector<int64_t> lst(P);
    std::vector<T> row(R);
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
      for (int64_t j = jmax - 1; j >= start; --j) {
        const int64_t gid = ids[j], n = pair_gauss[gid];
        const T u = means2d[2 * gid], v = means2d[2 * gid + 1], op = opac[n], z = depths[gid];
        const T* con = conics + 3 * gid;
        const T* f = feats + n * g.dim;
        const T log_thr = std::log(op * T(255)) + T(1e-6);
        int64_t c0, c1, r0, r1;
        pixel_rect(g, tx, ty, u, v, extents + 2 * gid, c0, c1, r0, r1);
        std::fill(row.begin(), row.end(), T(0));
        for (int64_t r = r0; r <= r1; ++r)
        for (int64_t cc = c0; cc <= c1; ++cc) {
          const int64_t p = r * g.tile + cc;
          if (j >= lst[p]) continue;
          const T px = T(tx * g.tile + cc) + T(0.5);
          const T py = T(ty * g.tile + r) + T(0.5);
          T dx, dy, power, alpha;
          bool clamped;
          if (!eval_alpha(u, v, con, op, log_thr, px, py, dx, dy, power, alpha, clamped)) continue;
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
          const T e = alpha / op;
          row[5] += dalpha * e;
          if (power <= T(0)) continue;
          const T dpow = -dalpha * alpha;
          row[0] -= dpow * (con[0] * dx + con[1] * dy);
          row[1] -= dpow * (con[1] * dx + con[2] * dy);
          row[2] += dpow * T(0.5) * dx * dx;
          row[3] += dpow * dx * dy;
          row[4] += dpow * T(0.5) * dy * dy;
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
  auto out = torch::zeros({num_cams, height, width, g.dim + 2}, opts);
  auto t_final = torch::ones({num_cams, height, width}, opts);
  auto last = torch::zeros({num_cams, height, width}, opts.dtype(torch::kInt64));
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
