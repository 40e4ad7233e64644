// Tile binning and front-to-back compositing of screen-space Gaussians on the CPU, and the
// backward pass, with the rules of edygs_ns/render/torch_backend.py (the reference):
//   * a Gaussian enters the 8x8 tiles of its 3-sigma square (radius from the projection), cut to
//     the tiles whose pixel centres its alpha >= ALPHA_MIN ellipse can reach;
//   * per pixel, depth order: alpha = min(ALPHA_MAX, o exp(power)), skipped unless alpha > ALPHA_MIN;
//     a pixel stops before the Gaussian that would take its transmittance to <= TRANSMITTANCE_MIN.
// Channels composited: the D features, the depth and 1 (the accumulated alpha): F = D + 2.
// Work is done per tile (OpenMP over tiles), one Gaussian at a time over the rows of pixels
// its ellipse reaches; a row of the tile is one short loop the compiler vectorises.
// The backward walks each tile front to back again; the gradient of the Gaussians behind a
// Gaussian is the composited total minus the running prefix (no division by 1 - alpha).

#ifndef RASTER_KERNELS_ONLY
#include <torch/extension.h>
#endif

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <numeric>
#include <vector>

namespace {

struct Rules {
  double alpha_max, alpha_min, trans_min, cull_margin, min_opacity;
};

// exp for float, branch-free so the row loops vectorise: Cody-Waite reduction to |r| <= ln2 / 2
// and a degree-7 Taylor polynomial (relative error ~1e-7); inputs below -80 give exp(-80).
inline float exp_row(float x) {
  x = x < -80.0f ? -80.0f : x;
  const float n = std::nearbyint(x * 1.44269504088896341f);
  const float r = (x - n * 0.693145751953125f) - n * 1.428606765330187e-06f;
  float p = 1.0f / 5040.0f;
  p = p * r + 1.0f / 720.0f;
  p = p * r + 1.0f / 120.0f;
  p = p * r + 1.0f / 24.0f;
  p = p * r + 1.0f / 6.0f;
  p = p * r + 0.5f;
  p = p * r + 1.0f;
  p = p * r + 1.0f;
  const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof(scale));
  return p * scale;
}

inline double exp_row(double x) { return std::exp(x); }

// The Gaussian's exponent at offset (dx, dy) = pixel centre - mean; one expression for forward and
// backward so both passes see the same alphas bit for bit.
template <typename scalar_t>
inline scalar_t power_at(scalar_t dx, scalar_t dy, scalar_t a, scalar_t b, scalar_t c) {
  return scalar_t(-0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
}

// Per (camera, Gaussian) record, scalar_t: mean x, y, conic a, b, c, opacity, D features, depth.
constexpr int kHead = 6;

template <typename scalar_t>
struct Scene {
  int64_t n_cams, n, n_feat;  // n_feat = D
  int width, height, tile, tiles_x, tiles_y;
  std::vector<scalar_t> records;  // [C * N, kHead + D + 1]
  std::vector<int32_t> rows;      // [C * N, 2] first / last pixel row the ellipse box reaches
  std::vector<int32_t> tiles;     // [C * N, 4] tile range x0, x1, y0, y1 (empty when culled)
  int64_t stride() const { return kHead + n_feat + 1; }
};

// Raw inputs: means2d [C, N, 2], conics [C, N, 3], opacities [N], features [N, D] or [C, N, D],
// depths [C, N], radii [C, N] (0 = culled); all contiguous.
template <typename scalar_t>
struct Inputs {
  const scalar_t *means2d, *conics, *opacities, *features, *depths;
  const int32_t* radii;
  int64_t n_cams, n, n_feat;
  bool per_camera;
  int width, height;
};

// Pack the per-Gaussian inputs and compute each Gaussian's tile range and pixel-row range.
template <typename scalar_t>
Scene<scalar_t> pack(const Inputs<scalar_t>& in, int tile, const Rules& rules, int threads) {
  Scene<scalar_t> s;
  s.n_cams = in.n_cams;
  s.n = in.n;
  s.n_feat = in.n_feat;
  s.width = in.width;
  s.height = in.height;
  s.tile = tile;
  s.tiles_x = (in.width + tile - 1) / tile;
  s.tiles_y = (in.height + tile - 1) / tile;
  const int64_t total = s.n_cams * s.n, stride = s.stride(), d = s.n_feat;
  s.records.resize(total * stride);
  s.rows.resize(total * 2);
  s.tiles.resize(total * 4);
  const scalar_t* m2 = in.means2d;
  const scalar_t* co = in.conics;
  const scalar_t* op = in.opacities;
  const scalar_t* fe = in.features;
  const scalar_t* de = in.depths;
  const int32_t* ra = in.radii;
  const bool per_camera = in.per_camera;
  const scalar_t ts = static_cast<scalar_t>(tile);
  const scalar_t limit = static_cast<scalar_t>(std::max(in.width, in.height) + tile);
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t i = 0; i < total; ++i) {
    const int64_t g = i % s.n;
    scalar_t* rec = &s.records[i * stride];
    rec[0] = m2[2 * i];
    rec[1] = m2[2 * i + 1];
    rec[2] = co[3 * i];
    rec[3] = co[3 * i + 1];
    rec[4] = co[3 * i + 2];
    rec[5] = op[g];
    const scalar_t* f = fe + (per_camera ? i : g) * d;
    for (int64_t k = 0; k < d; ++k) rec[kHead + k] = f[k];
    rec[kHead + d] = de[i];
    int32_t* tr = &s.tiles[4 * i];
    tr[0] = tr[1] = tr[2] = tr[3] = 0;
    if (ra[i] <= 0) continue;
    // the 3-sigma square, in the input precision (the rule: same expressions as the reference)
    const scalar_t cx = rec[0], cy = rec[1], rad = static_cast<scalar_t>(ra[i]);
    auto clampi = [](scalar_t v, scalar_t hi) { return std::min(std::max(v, scalar_t(0)), hi); };
    scalar_t x0 = clampi(std::floor((cx - rad) / ts), s.tiles_x), x1 = clampi(std::ceil((cx + rad) / ts), s.tiles_x);
    scalar_t y0 = clampi(std::floor((cy - rad) / ts), s.tiles_y), y1 = clampi(std::ceil((cy + rad) / ts), s.tiles_y);
    // the box of pixel centres where alpha can reach ALPHA_MIN (with a margin: only drops zeros)
    const scalar_t a = rec[2], b = rec[3], c = rec[4];
    const scalar_t o = std::max(rec[5], static_cast<scalar_t>(rules.min_opacity));
    const scalar_t level = std::log(o / static_cast<scalar_t>(rules.alpha_min));
    const scalar_t r2 = 2 * std::max(level + static_cast<scalar_t>(rules.cull_margin), scalar_t(0));
    const scalar_t reach = r2 / (a * c - b * b);
    const scalar_t hx = std::sqrt(c * reach), hy = std::sqrt(a * reach);
    auto clampl = [limit](scalar_t v) { return std::min(std::max(v, -limit), limit); };
    const scalar_t fx = clampl(std::ceil(cx - hx - scalar_t(0.5))), lx = clampl(std::floor(cx + hx - scalar_t(0.5)));
    const scalar_t fy = clampl(std::ceil(cy - hy - scalar_t(0.5))), ly = clampl(std::floor(cy + hy - scalar_t(0.5)));
    if (!(fx <= lx) || !(fy <= ly)) continue;  // empty box (or NaN)
    x0 = std::max(x0, std::floor(fx / ts));
    y0 = std::max(y0, std::floor(fy / ts));
    x1 = std::max(std::min(x1, std::floor(lx / ts) + 1), x0);
    y1 = std::max(std::min(y1, std::floor(ly / ts) + 1), y0);
    tr[0] = static_cast<int32_t>(x0);
    tr[1] = static_cast<int32_t>(x1);
    tr[2] = static_cast<int32_t>(y0);
    tr[3] = static_cast<int32_t>(y1);
    s.rows[2 * i] = static_cast<int32_t>(fy);
    s.rows[2 * i + 1] = static_cast<int32_t>(ly);
  }
  return s;
}

// Tile lists: offsets [C * T + 1] into ids [M] (c * N + n), each tile's list in depth order.
template <typename scalar_t>
void bin(const Scene<scalar_t>& s, std::vector<int64_t>& offsets, std::vector<int32_t>& ids, int threads) {
  const int64_t n_tiles = static_cast<int64_t>(s.tiles_x) * s.tiles_y, stride = s.stride();
  offsets.assign(s.n_cams * n_tiles + 1, 0);
  std::vector<std::vector<int32_t>> per_cam(s.n_cams);
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int64_t c = 0; c < s.n_cams; ++c) {
    std::vector<int32_t>& ord = per_cam[c];
    for (int32_t g = 0; g < s.n; ++g) {
      const int32_t* tr = &s.tiles[4 * (c * s.n + g)];
      if (tr[1] > tr[0] && tr[3] > tr[2]) ord.push_back(g);
    }
    const scalar_t* depth = &s.records[c * s.n * stride + kHead + s.n_feat];
    std::sort(ord.begin(), ord.end(), [depth, stride](int32_t i, int32_t j) {
      const scalar_t di = depth[i * stride], dj = depth[j * stride];
      return di < dj || (di == dj && i < j);
    });
    int64_t* count = &offsets[c * n_tiles + 1];
    for (int32_t g : ord) {
      const int32_t* tr = &s.tiles[4 * (c * s.n + g)];
      for (int32_t y = tr[2]; y < tr[3]; ++y)
        for (int32_t x = tr[0]; x < tr[1]; ++x) ++count[y * s.tiles_x + x];
    }
  }
  std::partial_sum(offsets.begin(), offsets.end(), offsets.begin());
  ids.resize(offsets.back());
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int64_t c = 0; c < s.n_cams; ++c) {
    std::vector<int64_t> fill(offsets.begin() + c * n_tiles, offsets.begin() + (c + 1) * n_tiles);
    for (int32_t g : per_cam[c]) {
      const int32_t* tr = &s.tiles[4 * (c * s.n + g)];
      const int32_t flat = static_cast<int32_t>(c * s.n + g);
      for (int32_t y = tr[2]; y < tr[3]; ++y)
        for (int32_t x = tr[0]; x < tr[1]; ++x) ids[fill[y * s.tiles_x + x]++] = flat;
    }
  }
}

// Number of composited feature channels (D features + depth) known at compile time: NC > 0 fuses
// the channel loops into the pixel loop (the common D = 3, 4); NC = 0 reads it at run time.
template <int NC>
inline int64_t channels(int64_t runtime) { return NC > 0 ? NC : runtime; }

// Forward of one tile. acc: [F, P] (features, depth, alpha); stop: [P] list index of the Gaussian
// that ended the pixel (excluded), else the list length; used: [count] 1 where the Gaussian was
// composited into some pixel of the tile (the backward skips the others). A finished pixel (or one outside the
// image) has transmittance 0, which no later Gaussian passes. A Gaussian is evaluated on the rows
// of the tile its ellipse box reaches: pixels [lo, hi) of the row-major tile, one flat loop the
// compiler vectorises.
template <typename scalar_t, int TS, int NC>
void composite_tile(const Scene<scalar_t>& s, const int32_t* list, int32_t count, int tx, int ty,
                    const Rules& rules, scalar_t* acc, int32_t* stop, uint8_t* used) {
  constexpr int P = TS * TS;
  constexpr int kCheckEvery = 8;  // Gaussians between tests for a finished tile
  const int64_t stride = s.stride(), nc = channels<NC>(s.n_feat + 1);
  const int xb = tx * TS, yb = ty * TS;
  alignas(64) scalar_t pxs[P], pys[P], w[P], trans[P];
  for (int p = 0; p < P; ++p) {
    pxs[p] = static_cast<scalar_t>(xb + p % TS) + scalar_t(0.5);
    pys[p] = static_cast<scalar_t>(yb + p / TS) + scalar_t(0.5);
    trans[p] = (xb + p % TS >= s.width || yb + p / TS >= s.height) ? scalar_t(0) : scalar_t(1);
    stop[p] = count;
  }
  std::fill(acc, acc + (nc + 1) * P, scalar_t(0));
  scalar_t* acc_alpha = acc + nc * P;
  const scalar_t amax = rules.alpha_max, amin = rules.alpha_min, tmin = rules.trans_min;
  for (int32_t k = 0; k < count; ++k) {
    if (k % kCheckEvery == 0 && k > 0) {
      scalar_t live = 0;
#pragma omp simd reduction(max : live)
      for (int p = 0; p < P; ++p) live = live > trans[p] ? live : trans[p];
      if (live == 0) break;
    }
    const int32_t id = list[k];
    const scalar_t* rec = &s.records[id * stride];
    const int lo = std::max(s.rows[2 * id] - yb, 0) * TS, hi = (std::min(s.rows[2 * id + 1] - yb, TS - 1) + 1) * TS;
    const scalar_t mx = rec[0], my = rec[1], a = rec[2], b = rec[3], c = rec[4], o = rec[5];
    const scalar_t* f = rec + kHead;
    int any = 0;
#pragma omp simd reduction(| : any)
    for (int p = lo; p < hi; ++p) {
      scalar_t alpha = o * exp_row(power_at(pxs[p] - mx, pys[p] - my, a, b, c));
      alpha = alpha < amax ? alpha : amax;
      const scalar_t t = trans[p];
      const scalar_t next = t * (scalar_t(1) - alpha);
      const bool ok = (t > 0) & (alpha > amin);
      const bool fin = ok & (next <= tmin);
      const bool inc = ok & !fin;
      const scalar_t wi = inc ? alpha * t : scalar_t(0);
      trans[p] = fin ? scalar_t(0) : (inc ? next : t);
      stop[p] = fin ? k : stop[p];
      any |= inc ? 1 : 0;
      acc_alpha[p] += wi;
      if constexpr (NC > 0) {
        for (int ch = 0; ch < NC; ++ch) acc[ch * P + p] += wi * f[ch];
      } else {
        w[p] = wi;
      }
    }
    used[k] = any ? 1 : 0;
    if constexpr (NC == 0) {
      for (int64_t ch = 0; ch < nc; ++ch) {
        const scalar_t fc = f[ch];
        scalar_t* o_ch = acc + ch * P;
#pragma omp simd
        for (int p = lo; p < hi; ++p) o_ch[p] += w[p] * fc;
      }
    }
  }
}

// Backward of one tile: per-intersection gradients [count, K] with K = 6 + D + 1:
// d/d mean x, y, d/d conic a, b, c, d/d log(opacity), d/d features, d/d depth.
// g: [F, P] dL/d(acc); total: [P] g . acc (the gradient-weighted composite of every Gaussian).
template <typename scalar_t, int TS, int NC>
void backward_tile(const Scene<scalar_t>& s, const int32_t* list, int32_t count, int tx, int ty,
                   const Rules& rules, const scalar_t* g, const scalar_t* total, const int32_t* stop,
                   const uint8_t* used, scalar_t* grads) {
  constexpr int P = TS * TS;
  const int64_t stride = s.stride(), nc = channels<NC>(s.n_feat + 1), n_k = kHead + nc;
  const int xb = tx * TS, yb = ty * TS;
  alignas(64) scalar_t pxs[P], pys[P], w[P], h[P], trans[P], prefix[P];
  int32_t last = 0;
  for (int p = 0; p < P; ++p) {
    pxs[p] = static_cast<scalar_t>(xb + p % TS) + scalar_t(0.5);
    pys[p] = static_cast<scalar_t>(yb + p / TS) + scalar_t(0.5);
    trans[p] = 1;
    prefix[p] = 0;
    last = std::max(last, stop[p]);
  }
  const scalar_t amax = rules.alpha_max, amin = rules.alpha_min;
  const scalar_t* g_alpha_ch = g + nc * P;  // the alpha channel's feature is 1
  for (int32_t k = 0; k < std::min(last, count); ++k) {
    if (!used[k]) {  // composited nowhere in this tile: its gradients here are 0
      std::fill(grads + static_cast<int64_t>(k) * n_k, grads + static_cast<int64_t>(k + 1) * n_k, scalar_t(0));
      continue;
    }
    const int32_t id = list[k];
    const scalar_t* rec = &s.records[id * stride];
    const int lo = std::max(s.rows[2 * id] - yb, 0) * TS, hi = (std::min(s.rows[2 * id + 1] - yb, TS - 1) + 1) * TS;
    const scalar_t mx = rec[0], my = rec[1], a = rec[2], b = rec[3], c = rec[4], o = rec[5];
    const scalar_t* f = rec + kHead;
    scalar_t* out = grads + static_cast<int64_t>(k) * n_k;
    if constexpr (NC == 0) {
#pragma omp simd
      for (int p = lo; p < hi; ++p) h[p] = g_alpha_ch[p];
      for (int64_t ch = 0; ch < nc; ++ch) {
        const scalar_t fc = f[ch];
        const scalar_t* g_ch = g + ch * P;
#pragma omp simd
        for (int p = lo; p < hi; ++p) h[p] += g_ch[p] * fc;
      }
    }
    scalar_t s_mx = 0, s_my = 0, s_a = 0, s_b = 0, s_c = 0, s_lo = 0;
    // feature sums as scalars (an array reduction is combined lane by lane, ~3x slower here)
    static_assert(NC <= 5, "fused channel count above 5");
    scalar_t s_f0 = 0, s_f1 = 0, s_f2 = 0, s_f3 = 0, s_f4 = 0;
#pragma omp simd reduction(+ : s_mx, s_my, s_a, s_b, s_c, s_lo, s_f0, s_f1, s_f2, s_f3, s_f4)
    for (int p = lo; p < hi; ++p) {
      scalar_t hp;
      if constexpr (NC > 0) {
        hp = g_alpha_ch[p];
        for (int ch = 0; ch < NC; ++ch) hp += g[ch * P + p] * f[ch];
      } else {
        hp = h[p];
      }
      const scalar_t dx = pxs[p] - mx, dy = pys[p] - my;
      const scalar_t raw = o * exp_row(power_at(dx, dy, a, b, c));
      const bool unclamped = raw < amax;
      const scalar_t alpha = unclamped ? raw : amax;
      const bool vis = (k < stop[p]) & (alpha > amin);
      const scalar_t t = trans[p];
      const scalar_t wi = vis ? alpha * t : scalar_t(0);
      const scalar_t pre = prefix[p] + wi * hp;
      prefix[p] = pre;
      const scalar_t g_alpha = t * hp - (total[p] - pre) / (scalar_t(1) - alpha);
      const scalar_t g_pow = (vis & unclamped) ? g_alpha * alpha : scalar_t(0);
      trans[p] = vis ? t * (scalar_t(1) - alpha) : t;
      s_mx += g_pow * (a * dx + b * dy);
      s_my += g_pow * (b * dx + c * dy);
      s_a += g_pow * dx * dx;
      s_b += g_pow * dx * dy;
      s_c += g_pow * dy * dy;
      s_lo += g_pow;
      if constexpr (NC > 0) {
        s_f0 += wi * g[p];
        if constexpr (NC > 1) s_f1 += wi * g[P + p];
        if constexpr (NC > 2) s_f2 += wi * g[2 * P + p];
        if constexpr (NC > 3) s_f3 += wi * g[3 * P + p];
        if constexpr (NC > 4) s_f4 += wi * g[4 * P + p];
      } else {
        w[p] = wi;
      }
    }
    out[0] = s_mx;
    out[1] = s_my;
    out[2] = scalar_t(-0.5) * s_a;
    out[3] = -s_b;
    out[4] = scalar_t(-0.5) * s_c;
    out[5] = s_lo;
    if constexpr (NC > 0) {
      const scalar_t sums[5] = {s_f0, s_f1, s_f2, s_f3, s_f4};
      for (int ch = 0; ch < NC; ++ch) out[kHead + ch] = sums[ch];
    } else {
      for (int64_t ch = 0; ch < nc; ++ch) {
        const scalar_t* g_ch = g + ch * P;
        scalar_t sum = 0;
#pragma omp simd reduction(+ : sum)
        for (int p = lo; p < hi; ++p) sum += w[p] * g_ch[p];
        out[kHead + ch] = sum;
      }
    }
  }
  // the Gaussians behind every pixel's stop get no gradient from this tile
  std::fill(grads + std::min<int64_t>(last, count) * n_k, grads + static_cast<int64_t>(count) * n_k, scalar_t(0));
}

// Forward of every tile: colour [C, H, W, D], depth and alpha [C, H, W] (every pixel written),
// stops [C * T * P]; the tile
// lists are returned for the backward.
template <typename scalar_t, int TS, int NC>
void forward_all(const Inputs<scalar_t>& in, const Rules& rules, int threads, scalar_t* colour, scalar_t* depth,
                 scalar_t* alpha, int32_t* stops,
                 std::vector<int64_t>& offsets, std::vector<int32_t>& ids, std::vector<uint8_t>& used) {
  constexpr int P = TS * TS;
  const Scene<scalar_t> s = pack<scalar_t>(in, TS, rules, threads);
  bin(s, offsets, ids, threads);
  used.assign(ids.size(), 0);
  const int64_t n_tiles = static_cast<int64_t>(s.tiles_x) * s.tiles_y, n_ch = s.n_feat + 2;
  const int width = in.width, height = in.height;
#pragma omp parallel num_threads(threads)
  {
    std::vector<scalar_t> acc(n_ch * P);
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < s.n_cams * n_tiles; ++t) {
      const int64_t c = t / n_tiles, local = t % n_tiles;
      const int tx = static_cast<int>(local % s.tiles_x), ty = static_cast<int>(local / s.tiles_x);
      composite_tile<scalar_t, TS, NC>(s, ids.data() + offsets[t], static_cast<int32_t>(offsets[t + 1] - offsets[t]),
                                       tx, ty, rules, acc.data(), stops + t * P, used.data() + offsets[t]);
      for (int p = 0; p < P; ++p) {
        const int x = tx * TS + p % TS, y = ty * TS + p / TS;
        if (x >= width || y >= height) continue;
        const int64_t pix = (c * height + y) * width + x;
        for (int64_t ch = 0; ch < n_ch - 2; ++ch) colour[pix * (n_ch - 2) + ch] = acc[ch * P + p];
        depth[pix] = acc[(n_ch - 2) * P + p];
        alpha[pix] = acc[(n_ch - 1) * P + p];
      }
    }
  }
}

// Backward of every tile, then the per-intersection gradients summed per Gaussian. Outputs:
// g_means2d [C, N, 2], g_conics [C, N, 3], g_depths [C, N] (overwritten), g_opacities [N] and
// g_features (shape of the features; both zero-filled by the caller).
template <typename scalar_t, int TS, int NC>
void backward_all(const Inputs<scalar_t>& in, const Rules& rules, int threads, const int64_t* offsets,
                  const int32_t* ids, const uint8_t* used, int64_t n_isect, const int32_t* stops,
                  const scalar_t* const outs[3], const scalar_t* const grad_outs[3], scalar_t* gm, scalar_t* gc, scalar_t* gd, scalar_t* go, scalar_t* gf) {
  constexpr int P = TS * TS;
  const Scene<scalar_t> s = pack<scalar_t>(in, TS, rules, threads);
  const int64_t n_tiles = static_cast<int64_t>(s.tiles_x) * s.tiles_y, d = s.n_feat, n_ch = d + 2;
  const int64_t n_k = kHead + d + 1;
  const int width = in.width, height = in.height;
  std::unique_ptr<scalar_t[]> grads(new scalar_t[std::max<int64_t>(n_isect * n_k, 1)]);  // every row written
#pragma omp parallel num_threads(threads)
  {
    std::vector<scalar_t> g(n_ch * P), total(P);
    std::vector<int32_t> stop(P);
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < s.n_cams * n_tiles; ++t) {
      const int64_t c = t / n_tiles, local = t % n_tiles;
      const int tx = static_cast<int>(local % s.tiles_x), ty = static_cast<int>(local / s.tiles_x);
      for (int p = 0; p < P; ++p) {
        const int x = tx * TS + p % TS, y = ty * TS + p / TS;
        total[p] = 0;
        if (x >= width || y >= height) {
          stop[p] = 0;
          for (int64_t ch = 0; ch < n_ch; ++ch) g[ch * P + p] = 0;
          continue;
        }
        stop[p] = stops[t * P + p];
        const int64_t pix = (c * height + y) * width + x;
        for (int64_t ch = 0; ch < n_ch; ++ch) {
          // channels: D colours, then depth, then alpha (one value per pixel each)
          const int plane = ch < d ? 0 : static_cast<int>(ch - d + 1);
          const int64_t at = plane == 0 ? pix * d + ch : pix;
          g[ch * P + p] = grad_outs[plane][at];
          total[p] += grad_outs[plane][at] * outs[plane][at];
        }
      }
      backward_tile<scalar_t, TS, NC>(s, ids + offsets[t], static_cast<int32_t>(offsets[t + 1] - offsets[t]), tx, ty,
                                  rules, g.data(), total.data(), stop.data(), used + offsets[t], grads.get() + offsets[t] * n_k);
    }
  }
  // sum the intersections of each Gaussian (serial: the lists of one Gaussian span many tiles)
  std::vector<scalar_t> per(s.n_cams * s.n * n_k, scalar_t(0));
  for (int64_t m = 0; m < n_isect; ++m) {
    scalar_t* dst = &per[static_cast<int64_t>(ids[m]) * n_k];
    const scalar_t* src = &grads[m * n_k];
    for (int64_t j = 0; j < n_k; ++j) dst[j] += src[j];
  }
  for (int64_t i = 0; i < s.n_cams * s.n; ++i) {
    const scalar_t* src = &per[i * n_k];
    const int64_t gi = i % s.n;
    gm[2 * i] = src[0];
    gm[2 * i + 1] = src[1];
    gc[3 * i] = src[2];
    gc[3 * i + 1] = src[3];
    gc[3 * i + 2] = src[4];
    go[gi] += src[5];  // d / d log(opacity) for now
    scalar_t* dst = gf + (in.per_camera ? i : gi) * d;
    for (int64_t k = 0; k < d; ++k) dst[k] += src[kHead + k];
    gd[i] = src[kHead + d];
  }
  const scalar_t min_o = static_cast<scalar_t>(rules.min_opacity);
  for (int64_t gi = 0; gi < s.n; ++gi) {
    const scalar_t o = in.opacities[gi];
    go[gi] = o >= min_o ? go[gi] / o : scalar_t(0);
  }
}

}  // namespace

#ifdef RASTER_KERNELS_ONLY
// Standalone build of the kernels (vectorisation reports, no torch headers).
__attribute__((used)) void kernels_float8(const Inputs<float>& in, const Rules& rules, float* out, int32_t* stops,
                    std::vector<int64_t>& offsets, std::vector<int32_t>& ids, std::vector<uint8_t>& used, float* g) {
  forward_all<float, 8, 5>(in, rules, 1, out, out, out, stops, offsets, ids, used);
  const float* const three[3] = {out, out, out};
  backward_all<float, 8, 5>(in, rules, 1, offsets.data(), ids.data(), used.data(), static_cast<int64_t>(ids.size()), stops,
                            three, three,
                         g, g, g, g, g);
}
#else

namespace {

Rules rules_from(const std::vector<double>& v) {
  TORCH_CHECK(v.size() == 5, "raster_cpu: rules are alpha_max, alpha_min, trans_min, cull_margin, min_opacity");
  return Rules{v[0], v[1], v[2], v[3], v[4]};
}

template <typename scalar_t>
Inputs<scalar_t> inputs_of(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                           const at::Tensor& features, const at::Tensor& depths, const at::Tensor& radii,
                           int64_t width, int64_t height) {
  for (const at::Tensor* t : {&means2d, &conics, &opacities, &features, &depths}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "raster_cpu: inputs must be contiguous CPU tensors");
    TORCH_CHECK(t->scalar_type() == means2d.scalar_type(), "raster_cpu: inputs must share one dtype");
  }
  TORCH_CHECK(radii.scalar_type() == at::kInt && radii.is_contiguous(), "raster_cpu: radii must be contiguous int32");
  return Inputs<scalar_t>{means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(),
                          features.data_ptr<scalar_t>(), depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(),
                          means2d.size(0), means2d.size(1), features.size(-1), features.dim() == 3,
                          static_cast<int>(width), static_cast<int>(height)};
}

// Calls fn(scalar, tile, channels) with compile-time values: float32 / float64, 8x8 tiles, and the
// composited feature channels (D + 1) fused for D = 3 (RGB) and D = 4 (RGB + mask), else generic.
template <typename Fn>
auto dispatch(const at::Tensor& like, int64_t tile, int64_t n_feat, Fn&& fn) {
  TORCH_CHECK(tile == 8, "raster_cpu: the tile size must be 8, got ", tile);
  using T8 = std::integral_constant<int, 8>;
  auto by_channels = [&](auto scalar) {
    if (n_feat == 3) return fn(scalar, T8(), std::integral_constant<int, 4>());
    if (n_feat == 4) return fn(scalar, T8(), std::integral_constant<int, 5>());
    return fn(scalar, T8(), std::integral_constant<int, 0>());
  };
  if (like.scalar_type() == at::kFloat) return by_channels(float());
  TORCH_CHECK(like.scalar_type() == at::kDouble, "raster_cpu: float32 or float64 only, got ", like.scalar_type());
  return by_channels(double());
}

}  // namespace

std::vector<at::Tensor> rasterize_forward(const at::Tensor& means2d, const at::Tensor& conics,
                                          const at::Tensor& opacities, const at::Tensor& features,
                                          const at::Tensor& depths, const at::Tensor& radii, int64_t width,
                                          int64_t height, int64_t tile, const std::vector<double>& rules) {
  const Rules r = rules_from(rules);
  return dispatch(means2d, tile, features.size(-1), [&](auto scalar, auto ts, auto nc) {
    using scalar_t = decltype(scalar);
    constexpr int TS = decltype(ts)::value, NC = decltype(nc)::value;
    const Inputs<scalar_t> in = inputs_of<scalar_t>(means2d, conics, opacities, features, depths, radii, width, height);
    const int64_t n_tiles = ((width + TS - 1) / TS) * ((height + TS - 1) / TS);
    at::Tensor colour = at::empty({in.n_cams, height, width, in.n_feat}, means2d.options());
    at::Tensor depth = at::empty({in.n_cams, height, width, 1}, means2d.options());
    at::Tensor alpha = at::empty({in.n_cams, height, width, 1}, means2d.options());
    at::Tensor stops = at::empty({in.n_cams * n_tiles * TS * TS}, radii.options());
    std::vector<int64_t> offsets;
    std::vector<int32_t> ids;
    std::vector<uint8_t> used;
    forward_all<scalar_t, TS, NC>(in, r, at::get_num_threads(), colour.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
                                  alpha.data_ptr<scalar_t>(), stops.data_ptr<int32_t>(),
                                  offsets, ids, used);
    at::Tensor offsets_t = at::empty({static_cast<int64_t>(offsets.size())}, at::kLong);
    std::memcpy(offsets_t.data_ptr<int64_t>(), offsets.data(), offsets.size() * sizeof(int64_t));
    at::Tensor ids_t = at::empty({static_cast<int64_t>(ids.size())}, at::kInt);
    if (!ids.empty()) std::memcpy(ids_t.data_ptr<int32_t>(), ids.data(), ids.size() * sizeof(int32_t));
    at::Tensor used_t = at::empty({static_cast<int64_t>(used.size())}, at::kByte);
    if (!used.empty()) std::memcpy(used_t.data_ptr<uint8_t>(), used.data(), used.size());
    return std::vector<at::Tensor>{colour, depth, alpha, offsets_t, ids_t, used_t, stops};
  });
}

std::vector<at::Tensor> rasterize_backward(const at::Tensor& means2d, const at::Tensor& conics,
                                           const at::Tensor& opacities, const at::Tensor& features,
                                           const at::Tensor& depths, const at::Tensor& radii, int64_t width,
                                           int64_t height, int64_t tile, const std::vector<double>& rules,
                                           const at::Tensor& offsets, const at::Tensor& ids, const at::Tensor& used,
                                           const at::Tensor& stops, const std::vector<at::Tensor>& outs,
                                           const std::vector<at::Tensor>& grad_outs) {
  TORCH_CHECK(outs.size() == 3 && grad_outs.size() == 3, "raster_cpu: colour, depth and alpha and their gradients");
  for (int i = 0; i < 3; ++i) {
    TORCH_CHECK(grad_outs[i].is_contiguous() && outs[i].is_contiguous() && grad_outs[i].sizes() == outs[i].sizes(),
                "raster_cpu: each gradient must be contiguous and match its output");
  }
  TORCH_CHECK(used.scalar_type() == at::kByte && used.numel() == ids.numel(), "raster_cpu: used must match ids");
  const Rules r = rules_from(rules);
  return dispatch(means2d, tile, features.size(-1), [&](auto scalar, auto ts, auto nc) {
    using scalar_t = decltype(scalar);
    constexpr int TS = decltype(ts)::value, NC = decltype(nc)::value;
    const Inputs<scalar_t> in = inputs_of<scalar_t>(means2d, conics, opacities, features, depths, radii, width, height);
    at::Tensor g_means2d = at::empty_like(means2d), g_conics = at::empty_like(conics);
    at::Tensor g_depths = at::empty_like(depths), g_opacities = at::zeros_like(opacities);
    at::Tensor g_features = at::zeros_like(features);
    const scalar_t* const out_p[3] = {outs[0].data_ptr<scalar_t>(), outs[1].data_ptr<scalar_t>(),
                                      outs[2].data_ptr<scalar_t>()};
    const scalar_t* const grad_p[3] = {grad_outs[0].data_ptr<scalar_t>(), grad_outs[1].data_ptr<scalar_t>(),
                                       grad_outs[2].data_ptr<scalar_t>()};
    backward_all<scalar_t, TS, NC>(in, r, at::get_num_threads(), offsets.data_ptr<int64_t>(), ids.data_ptr<int32_t>(),
                                   used.data_ptr<uint8_t>(), ids.numel(), stops.data_ptr<int32_t>(), out_p, grad_p,
                                   g_means2d.data_ptr<scalar_t>(), g_conics.data_ptr<scalar_t>(),
                                   g_depths.data_ptr<scalar_t>(), g_opacities.data_ptr<scalar_t>(),
                                   g_features.data_ptr<scalar_t>());
    return std::vector<at::Tensor>{g_means2d, g_conics, g_opacities, g_features, g_depths};
  });
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &rasterize_forward, "tile binning and compositing (CPU)");
  m.def("backward", &rasterize_backward, "gradients of rasterize_forward's first output (CPU)");
}

#endif  // RASTER_KERNELS_ONLY
