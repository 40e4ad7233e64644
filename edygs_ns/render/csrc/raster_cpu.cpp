// Tile binning and front-to-back compositing of screen-space Gaussians on the CPU, and the
// backward pass, with the rules of edygs_ns/render/torch_backend.py (the reference):
//   * a Gaussian enters the 8x8 tiles of its 3-sigma square (radius from the projection), cut to
//     the tiles whose pixel centres its alpha >= ALPHA_MIN ellipse can reach;
//   * per pixel, depth order: alpha = min(ALPHA_MAX, o exp(power)), skipped unless alpha > ALPHA_MIN;
//     a pixel stops before the Gaussian that would take its transmittance to <= TRANSMITTANCE_MIN.
// Channels composited: the D features, the depth and 1 (the accumulated alpha).
// The visible Gaussians are packed in depth order (per camera) and the tile lists index that
// packed array, so a tile walks it front to back at increasing addresses. Work is done per tile
// (OpenMP over tiles) in 64-byte vectors ("chunks": two rows of a tile in float32, one in float64),
// one Gaussian at a time over the chunks its ellipse box reaches.
// The backward walks each tile front to back again; the gradient of the Gaussians behind a
// Gaussian is the composited total minus the running prefix (no division of the transmittance).
// Per (Gaussian, tile) the gradient sums stay in vector registers over the chunks and are added
// once into a per-thread, per-Gaussian buffer.
// Also here: the EWA projection of edygs_ns/render/projection.py and its closed-form backward.

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

#ifdef _OPENMP
#include <omp.h>
#endif
#if defined(__AVX512F__)
#include <immintrin.h>
#endif

namespace {

struct Rules {
  double alpha_max, alpha_min, trans_min, cull_margin, min_opacity;
};

// 64-byte vectors (GCC vector extensions): V holds L pixels, M is the matching lane mask
// (all ones where true). One AVX-512 register here; two AVX2 registers on CPUs without it.
template <typename T>
struct Simd;
template <>
struct Simd<float> {
  typedef float V __attribute__((vector_size(64)));
  typedef int32_t M __attribute__((vector_size(64)));
  typedef uint32_t Key;
  static constexpr int L = 16;
};
template <>
struct Simd<double> {
  typedef double V __attribute__((vector_size(64)));
  typedef int64_t M __attribute__((vector_size(64)));
  typedef uint64_t Key;
  static constexpr int L = 8;
};

template <typename T>
using VecOf = typename Simd<T>::V;
template <typename T>
using MaskOf = typename Simd<T>::M;

// exp for float, lane by lane without branches: Cody-Waite reduction to |r| <= ln2 / 2 and a
// degree-7 Taylor polynomial (relative error ~1e-7); inputs below -80 give exp(-80). The
// rounding to the nearest integer adds and subtracts 1.5 * 2^23 (exact for |x| < 2^22).
inline Simd<float>::V exp_vec(Simd<float>::V x) {
  typedef Simd<float>::V V;
  typedef Simd<float>::M M;
  const V floor_v = V{} - 80.0f;
  x = x < floor_v ? floor_v : x;
  const V shifter = V{} + 12582912.0f;
  const V n = (x * 1.44269504088896341f + shifter) - shifter;
  const V r = (x - n * 0.693145751953125f) - n * 1.428606765330187e-06f;
  V p = V{} + 1.0f / 5040.0f;
  p = p * r + 1.0f / 720.0f;
  p = p * r + 1.0f / 120.0f;
  p = p * r + 1.0f / 24.0f;
  p = p * r + 1.0f / 6.0f;
  p = p * r + 0.5f;
  p = p * r + 1.0f;
  p = p * r + 1.0f;
  const M bits = (__builtin_convertvector(n, M) + 127) << 23;
  return p * (V)bits;  // a vector bit cast (no pointer pun)
}

// float64 (the parity tests): the library exp, lane by lane.
inline Simd<double>::V exp_vec(Simd<double>::V x) {
  Simd<double>::V out;
  for (int i = 0; i < Simd<double>::L; ++i) out[i] = std::exp(x[i]);
  return out;
}

// Whether any lane of a mask is set (64-byte masks; a bit cast, not a pointer pun, which GCC may
// reorder against the vector's writes).
template <typename M>
inline bool any_lane(const M& m) {
  static_assert(sizeof(M) == 64, "64-byte masks");
#if defined(__AVX512F__)
  const __m512i v = (__m512i)m;
  return _mm512_test_epi64_mask(v, v) != 0;
#else
  typedef uint64_t U __attribute__((vector_size(64)));
  const U w = (U)m;
  uint64_t acc = 0;
  for (int i = 0; i < 8; ++i) acc |= w[i];
  return acc != 0;
#endif
}

// Horizontal sums of many vectors at once: a tree of two-input shuffles ("fold") halves the lanes
// of each vector while pairing vectors up, so K vectors of L lanes take about K fold steps instead
// of K separate horizontal sums. fold<H>(a, b): lane q takes the sum of lanes s and s + H of a (or
// of b, for the upper half of each 2H-lane block), s = its block's start + q % H.
template <typename scalar_t>
MaskOf<scalar_t> fold_index(int h, bool upper) {
  MaskOf<scalar_t> ix;
  constexpr int L = Simd<scalar_t>::L;
  for (int q = 0; q < L; ++q) {
    const int blk = q / (2 * h), within = q % (2 * h);
    ix[q] = (within < h ? 0 : L) + blk * 2 * h + within % h + (upper ? h : 0);
  }
  return ix;
}
template <typename scalar_t, int H>
const MaskOf<scalar_t> kFoldLo = fold_index<scalar_t>(H, false);
template <typename scalar_t, int H>
const MaskOf<scalar_t> kFoldHi = fold_index<scalar_t>(H, true);

template <typename scalar_t, int H>
inline VecOf<scalar_t> fold(const VecOf<scalar_t>& a, const VecOf<scalar_t>& b) {
  return __builtin_shuffle(a, b, kFoldLo<scalar_t, H>) + __builtin_shuffle(a, b, kFoldHi<scalar_t, H>);
}

// L vectors -> one vector of their L totals (in the lane order of fold_owner).
template <typename scalar_t>
inline VecOf<scalar_t> fold_all(VecOf<scalar_t>* w) {
  constexpr int L = Simd<scalar_t>::L;
  if constexpr (L == 16) {
    for (int i = 0; i < 8; ++i) w[i] = fold<scalar_t, 8>(w[2 * i], w[2 * i + 1]);
  }
  for (int i = 0; i < 4; ++i) w[i] = fold<scalar_t, 4>(w[2 * i], w[2 * i + 1]);
  for (int i = 0; i < 2; ++i) w[i] = fold<scalar_t, 2>(w[2 * i], w[2 * i + 1]);
  return fold<scalar_t, 1>(w[0], w[1]);
}

// Which input vector's total lands in each lane of fold_all (the same folds, on owner labels;
// not through kFold*, whose initialisation order relative to this one is unspecified).
template <typename scalar_t>
std::vector<int> fold_owner() {
  constexpr int L = Simd<scalar_t>::L;
  std::vector<std::vector<int>> own(L, std::vector<int>(L));
  for (int i = 0; i < L; ++i) std::fill(own[i].begin(), own[i].end(), i);
  for (int h = L / 2, count = L; h >= 1; h /= 2, count /= 2) {
    const MaskOf<scalar_t> ix = fold_index<scalar_t>(h, false);
    for (int i = 0; i < count / 2; ++i) {
      std::vector<int> merged(L);
      for (int q = 0; q < L; ++q) merged[q] = ix[q] < L ? own[2 * i][ix[q]] : own[2 * i + 1][ix[q] - L];
      own[i] = merged;
    }
  }
  return own[0];
}

// Lane of the folded vector that holds input vector j's total (the inverse of fold_owner).
template <typename scalar_t>
std::vector<int> fold_slot() {
  const std::vector<int> owner = fold_owner<scalar_t>();
  std::vector<int> slot(owner.size());
  for (size_t q = 0; q < owner.size(); ++q) slot[owner[q]] = static_cast<int>(q);
  return slot;
}
template <typename scalar_t>
const std::vector<int> kFoldSlot = fold_slot<scalar_t>();

// Folds K vectors into ceil(K / L) vectors of totals and adds them to out: the total of v[j] goes
// to lane kFoldSlot[j % L] of out[j / L].
template <typename scalar_t>
inline void fold_add(const VecOf<scalar_t>* v, int64_t K, VecOf<scalar_t>* out) {
  constexpr int L = Simd<scalar_t>::L;
  for (int64_t g0 = 0; g0 < K; g0 += L) {
    VecOf<scalar_t> w[L];
    for (int i = 0; i < L; ++i) w[i] = g0 + i < K ? v[g0 + i] : VecOf<scalar_t>{};
    out[g0 / L] += fold_all<scalar_t>(w);
  }
}

// 1 / x: on AVX-512 float lanes the 14-bit reciprocal estimate and one Newton step (relative
// error ~1e-8, below float's rounding), which does not hold the divider for 10+ cycles; else a
// division.
inline Simd<float>::V reciprocal(Simd<float>::V x) {
#if defined(__AVX512F__)
  typedef Simd<float>::V V;
  const V r = reinterpret_cast<V>(_mm512_rcp14_ps(reinterpret_cast<__m512>(x)));
  return r * (2.0f - x * r);
#else
  return 1.0f / x;
#endif
}
inline Simd<double>::V reciprocal(Simd<double>::V x) { return 1.0 / x; }

// The Gaussian's exponent at offset (dx, dy) = pixel centre - mean; one expression for forward and
// backward so both passes see the same alphas bit for bit.
template <typename V, typename S>
inline V power_at(const V& dx, const V& dy, S a, S b, S c) {
  return S(-0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
}

// Packed record of a visible (camera, Gaussian), scalar_t: mean x, y, conic a, b, c, opacity,
// D features, depth (the depth is composited as feature D).
constexpr int kHead = 6;

// Per (camera, Gaussian) geometry before sorting: tile range and pixel-row range of the box.
struct Footprint {
  int32_t x0, x1, y0, y1, row0, row1;
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

// The visible Gaussians in depth order: records [M, kHead + D + 1], rows [M, 2] (first / last
// pixel row of the box), order [M] (c * N + n of each record); camera c owns records
// [cam_start[c], cam_start[c + 1]). Tile lists (offsets [C * T + 1], ids [I]) index the records.
template <typename scalar_t>
struct Packed {
  int64_t n_feat;
  int width, height, tiles_x, tiles_y;
  const scalar_t* records;
  const int32_t* rows;
  int64_t stride() const { return kHead + n_feat + 1; }
};

// Tile and row range of every (camera, Gaussian); x1 == x0 when it reaches no tile.
template <typename scalar_t>
void footprints(const Inputs<scalar_t>& in, int tile, const Rules& rules, int threads, Footprint* out) {
  const int64_t total = in.n_cams * in.n;
  const int tiles_x = (in.width + tile - 1) / tile, tiles_y = (in.height + tile - 1) / tile;
  const scalar_t ts = static_cast<scalar_t>(tile);
  const scalar_t limit = static_cast<scalar_t>(std::max(in.width, in.height) + tile);
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t i = 0; i < total; ++i) {
    Footprint& fp = out[i];
    fp = Footprint{0, 0, 0, 0, 0, 0};
    if (in.radii[i] <= 0) continue;
    // the 3-sigma square, in the input precision (the rule: same expressions as the reference)
    const scalar_t cx = in.means2d[2 * i], cy = in.means2d[2 * i + 1], rad = static_cast<scalar_t>(in.radii[i]);
    auto clampi = [](scalar_t v, scalar_t hi) { return std::min(std::max(v, scalar_t(0)), hi); };
    scalar_t x0 = clampi(std::floor((cx - rad) / ts), tiles_x), x1 = clampi(std::ceil((cx + rad) / ts), tiles_x);
    scalar_t y0 = clampi(std::floor((cy - rad) / ts), tiles_y), y1 = clampi(std::ceil((cy + rad) / ts), tiles_y);
    // the box of pixel centres where alpha can reach ALPHA_MIN (with a margin: only drops zeros)
    const scalar_t a = in.conics[3 * i], b = in.conics[3 * i + 1], c = in.conics[3 * i + 2];
    const scalar_t o = std::max(in.opacities[i % in.n], static_cast<scalar_t>(rules.min_opacity));
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
    if (!(x1 > x0) || !(y1 > y0)) continue;
    fp = Footprint{static_cast<int32_t>(x0), static_cast<int32_t>(x1), static_cast<int32_t>(y0),
                   static_cast<int32_t>(y1), static_cast<int32_t>(fy), static_cast<int32_t>(ly)};
  }
}

// Order-preserving unsigned key of a float (ascending keys = ascending values; -0 < +0).
template <typename scalar_t>
inline typename Simd<scalar_t>::Key sort_key(scalar_t v) {
  typedef typename Simd<scalar_t>::Key Key;
  Key k;
  std::memcpy(&k, &v, sizeof(k));
  const Key sign = Key(1) << (8 * sizeof(Key) - 1);
  return (k & sign) ? ~k : (k | sign);
}

// Stable LSD radix sort of idx by key (8-bit digits; digits every key shares are skipped).
template <typename Key>
void radix_sort(std::vector<Key>& key, std::vector<int32_t>& idx) {
  const size_t n = key.size();
  std::vector<Key> key2(n);
  std::vector<int32_t> idx2(n);
  for (size_t shift = 0; shift < 8 * sizeof(Key); shift += 8) {
    size_t count[257] = {0};
    for (size_t i = 0; i < n; ++i) ++count[((key[i] >> shift) & 0xff) + 1];
    if (n == 0 || count[((key[0] >> shift) & 0xff) + 1] == n) continue;  // one digit value: a no-op pass
    for (int d = 0; d < 256; ++d) count[d + 1] += count[d];
    for (size_t i = 0; i < n; ++i) {
      const size_t at = count[(key[i] >> shift) & 0xff]++;
      key2[at] = key[i];
      idx2[at] = idx[i];
    }
    key.swap(key2);
    idx.swap(idx2);
  }
}

// Sort the visible Gaussians of each camera by depth (ties by index), pack their records and rows
// in that order, and build the tile lists. order / records / rows are resized to the visible count.
template <typename scalar_t>
void pack_and_bin(const Inputs<scalar_t>& in, int tile, const Rules& rules, int threads, std::vector<int32_t>& order,
                  std::vector<scalar_t>& records, std::vector<int32_t>& rows, std::vector<int64_t>& offsets,
                  std::vector<int32_t>& ids) {
  typedef typename Simd<scalar_t>::Key Key;
  const int64_t total = in.n_cams * in.n, d = in.n_feat, stride = kHead + d + 1;
  const int tiles_x = (in.width + tile - 1) / tile, tiles_y = (in.height + tile - 1) / tile;
  const int64_t n_tiles = static_cast<int64_t>(tiles_x) * tiles_y;
  std::unique_ptr<Footprint[]> fps(new Footprint[std::max<int64_t>(total, 1)]);
  footprints(in, tile, rules, threads, fps.get());
  // per camera: visible indices sorted by depth
  std::vector<std::vector<int32_t>> per_cam(in.n_cams);
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int64_t c = 0; c < in.n_cams; ++c) {
    std::vector<Key> key;
    std::vector<int32_t>& idx = per_cam[c];
    for (int32_t g = 0; g < in.n; ++g) {
      const Footprint& fp = fps[c * in.n + g];
      if (fp.x1 > fp.x0) {
        key.push_back(sort_key(in.depths[c * in.n + g]));
        idx.push_back(static_cast<int32_t>(c * in.n + g));
      }
    }
    radix_sort(key, idx);
  }
  std::vector<int64_t> cam_start(in.n_cams + 1, 0);
  for (int64_t c = 0; c < in.n_cams; ++c) cam_start[c + 1] = cam_start[c] + static_cast<int64_t>(per_cam[c].size());
  const int64_t m = cam_start[in.n_cams];
  order.resize(m);
  for (int64_t c = 0; c < in.n_cams; ++c) std::copy(per_cam[c].begin(), per_cam[c].end(), order.begin() + cam_start[c]);
  records.resize(std::max<int64_t>(m * stride, 1));
  rows.resize(std::max<int64_t>(2 * m, 1));
  std::vector<Footprint> sorted(m);
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t r = 0; r < m; ++r) {
    const int64_t i = order[r], g = i % in.n;
    scalar_t* rec = &records[r * stride];
    rec[0] = in.means2d[2 * i];
    rec[1] = in.means2d[2 * i + 1];
    rec[2] = in.conics[3 * i];
    rec[3] = in.conics[3 * i + 1];
    rec[4] = in.conics[3 * i + 2];
    rec[5] = in.opacities[g];
    const scalar_t* f = in.features + (in.per_camera ? i : g) * d;
    for (int64_t k = 0; k < d; ++k) rec[kHead + k] = f[k];
    rec[kHead + d] = in.depths[i];
    sorted[r] = fps[i];
    rows[2 * r] = fps[i].row0;
    rows[2 * r + 1] = fps[i].row1;
  }
  offsets.assign(in.n_cams * n_tiles + 1, 0);
  for (int64_t c = 0; c < in.n_cams; ++c) {
    int64_t* count = &offsets[c * n_tiles + 1];
    for (int64_t r = cam_start[c]; r < cam_start[c + 1]; ++r) {
      const Footprint& fp = sorted[r];
      for (int32_t y = fp.y0; y < fp.y1; ++y)
        for (int32_t x = fp.x0; x < fp.x1; ++x) ++count[y * tiles_x + x];
    }
  }
  std::partial_sum(offsets.begin(), offsets.end(), offsets.begin());
  ids.resize(offsets.back());
  std::vector<int64_t> fill(offsets.begin(), offsets.end() - 1);
  for (int64_t c = 0; c < in.n_cams; ++c) {
    int64_t* at = &fill[c * n_tiles];
    for (int64_t r = cam_start[c]; r < cam_start[c + 1]; ++r) {
      const Footprint& fp = sorted[r];
      for (int32_t y = fp.y0; y < fp.y1; ++y)
        for (int32_t x = fp.x0; x < fp.x1; ++x) ids[at[y * tiles_x + x]++] = static_cast<int32_t>(r);
    }
  }
}

// How many list entries ahead the tile loops prefetch a record (the records of a tile list are
// far apart in memory once the scene has many Gaussians).
constexpr int kPrefetch = 4;

template <typename scalar_t>
inline void prefetch_record(const Packed<scalar_t>& s, int32_t id) {
  __builtin_prefetch(&s.records[id * s.stride()]);
  __builtin_prefetch(&s.rows[2 * id]);
}

// Number of composited feature channels (D features + depth) known at compile time: NC > 0 fuses
// the channel loops (the common D = 3, 4); NC = 0 reads it at run time.
template <int NC>
inline int64_t channels(int64_t runtime) { return NC > 0 ? NC : runtime; }

// Chunks [c0, c1] of the tile (rows ty * TS .. + TS) that the record's box rows reach.
template <int TS, int RPC>
inline void chunk_range(const int32_t* rows, int yb, int& c0, int& c1) {
  c0 = std::max(rows[0] - yb, 0) / RPC;
  c1 = std::min(rows[1] - yb, TS - 1) / RPC;
}

// Forward of one tile, in chunks of L pixels (RPC = L / TS rows). acc: [nc + 1][NCH] vectors
// (features, depth, alpha); stop: [P] list index of the Gaussian that ended the pixel (excluded),
// else the list length; used: [count] 1 where the Gaussian was composited into some pixel of the
// tile (the backward skips the others). A finished pixel (or one outside the image) has
// transmittance 0, which no later Gaussian passes.
template <typename scalar_t, int TS, int NC>
void composite_tile(const Packed<scalar_t>& s, const int32_t* list, int32_t count, int tx, int ty, const Rules& rules,
                    VecOf<scalar_t>* acc, int32_t* stop_out, uint8_t* used) {
  typedef VecOf<scalar_t> V;
  typedef MaskOf<scalar_t> M;
  constexpr int L = Simd<scalar_t>::L, P = TS * TS, NCH = P / L, RPC = L / TS;
  static_assert(P % L == 0 && L % TS == 0, "tile and vector sizes");
  constexpr int kCheckEvery = 8;  // Gaussians between tests for a finished tile
  const int64_t stride = s.stride(), nc = channels<NC>(s.n_feat + 1);
  const int xb = tx * TS, yb = ty * TS;
  V px[NCH], py[NCH], trans[NCH];
  M stop[NCH];
  for (int q = 0; q < NCH; ++q) {
    for (int l = 0; l < L; ++l) {
      const int p = q * L + l, x = xb + p % TS, y = yb + p / TS;
      px[q][l] = static_cast<scalar_t>(x) + scalar_t(0.5);
      py[q][l] = static_cast<scalar_t>(y) + scalar_t(0.5);
      const bool outside = x >= s.width || y >= s.height;  // never composited; no backward work
      trans[q][l] = outside ? scalar_t(0) : scalar_t(1);
      stop[q][l] = outside ? 0 : count;
    }
  }
  for (int64_t i = 0; i < (nc + 1) * NCH; ++i) acc[i] = V{};
  V* acc_alpha = acc + nc * NCH;
  const scalar_t amax = rules.alpha_max, amin = rules.alpha_min, tmin = rules.trans_min;
  const V zero{}, one = V{} + scalar_t(1), v_amax = V{} + amax;
  for (int32_t k = 0; k < count; ++k) {
    if (k % kCheckEvery == 0 && k > 0) {
      M live{};
      for (int q = 0; q < NCH; ++q) live |= trans[q] > zero;
      if (!any_lane(live)) break;
    }
    const int32_t id = list[k];
    if (k + kPrefetch < count) prefetch_record(s, list[k + kPrefetch]);
    const scalar_t* rec = &s.records[id * stride];
    int c0, c1;
    chunk_range<TS, RPC>(&s.rows[2 * id], yb, c0, c1);
    const scalar_t mx = rec[0], my = rec[1], a = rec[2], b = rec[3], c = rec[4], o = rec[5];
    const scalar_t* f = rec + kHead;
    M any{};
    for (int q = c0; q <= c1; ++q) {
      V alpha = o * exp_vec(power_at(px[q] - mx, py[q] - my, a, b, c));
      alpha = alpha < v_amax ? alpha : v_amax;
      const V t = trans[q];
      const V next = t * (one - alpha);
      const M ok = (t > zero) & (alpha > amin);
      const M fin = ok & (next <= tmin);
      const M inc = ok & ~fin;
      const V wi = inc ? alpha * t : zero;
      trans[q] = fin ? zero : (inc ? next : t);
      stop[q] = fin ? (M{} + k) : stop[q];
      any |= inc;
      acc_alpha[q] += wi;
      for (int64_t ch = 0; ch < nc; ++ch) acc[ch * NCH + q] += wi * f[ch];
    }
    used[k] = any_lane(any) ? 1 : 0;
  }
  for (int q = 0; q < NCH; ++q)
    for (int l = 0; l < L; ++l) stop_out[q * L + l] = static_cast<int32_t>(stop[q][l]);
}

// Backward of one tile. Per (Gaussian, tile) the pixel sums S_j, j < K = kHead + nc, of g_pow (a dx
// + b dy), g_pow (b dx + c dy), g_pow dx^2, g_pow dx dy, g_pow dy^2, g_pow (= dL/d log opacity) and
// wi g_ch (features, depth), with g_pow = dL/d power; they are folded and added into the record's
// G = ceil(K / L) vectors per[id * G ...] (see fold_add), which the caller turns into gradients.
// g: [nc + 1][NCH] dL/d(acc); total: [NCH] g . acc (the gradient-weighted composite of every
// Gaussian); stop_in: [P]; scratch: [K] vectors (the generic path's sums).
template <typename scalar_t, int TS, int NC>
void backward_tile(const Packed<scalar_t>& s, const int32_t* list, int32_t count, int tx, int ty, const Rules& rules,
                   const VecOf<scalar_t>* g, const VecOf<scalar_t>* total, const int32_t* stop_in, const uint8_t* used,
                   VecOf<scalar_t>* scratch, VecOf<scalar_t>* per) {
  typedef VecOf<scalar_t> V;
  typedef MaskOf<scalar_t> M;
  constexpr int L = Simd<scalar_t>::L, P = TS * TS, NCH = P / L, RPC = L / TS;
  const int64_t stride = s.stride(), nc = channels<NC>(s.n_feat + 1), n_k = kHead + nc, groups = (n_k + L - 1) / L;
  const int xb = tx * TS, yb = ty * TS;
  V px[NCH], py[NCH], trans[NCH], prefix[NCH];
  M stop[NCH];
  int32_t last = 0;
  for (int q = 0; q < NCH; ++q) {
    for (int l = 0; l < L; ++l) {
      const int p = q * L + l;
      px[q][l] = static_cast<scalar_t>(xb + p % TS) + scalar_t(0.5);
      py[q][l] = static_cast<scalar_t>(yb + p / TS) + scalar_t(0.5);
      stop[q][l] = stop_in[p];
      last = std::max(last, stop_in[p]);
    }
    trans[q] = V{} + scalar_t(1);
    prefix[q] = V{};
  }
  const scalar_t amax = rules.alpha_max, amin = rules.alpha_min;
  const V zero{}, one = V{} + scalar_t(1), v_amax = V{} + amax;
  const V* g_alpha_ch = g + nc * NCH;  // the alpha channel's feature is 1
  V sums_fixed[kHead + (NC > 0 ? NC : 0)];
  V* sums = NC > 0 ? sums_fixed : scratch;
  V* sf = sums + kHead;
  for (int32_t k = 0; k < std::min(last, count); ++k) {
    if (!used[k]) continue;  // composited nowhere in this tile: its gradients here are 0
    const int32_t id = list[k];
    if (k + kPrefetch < count) prefetch_record(s, list[k + kPrefetch]);
    const scalar_t* rec = &s.records[id * stride];
    int c0, c1;
    chunk_range<TS, RPC>(&s.rows[2 * id], yb, c0, c1);
    const scalar_t mx = rec[0], my = rec[1], a = rec[2], b = rec[3], c = rec[4], o = rec[5];
    const scalar_t* f = rec + kHead;
    const M kv = M{} + k;
    for (int64_t j = 0; j < n_k; ++j) sums[j] = V{};
    for (int q = c0; q <= c1; ++q) {
      V hp = g_alpha_ch[q];
      for (int64_t ch = 0; ch < nc; ++ch) hp += g[ch * NCH + q] * f[ch];
      const V dx = px[q] - mx, dy = py[q] - my;
      const V raw = o * exp_vec(power_at(dx, dy, a, b, c));
      const M unclamped = raw < v_amax;
      const V alpha = unclamped ? raw : v_amax;
      const M vis = (kv < stop[q]) & (alpha > amin);
      if (!any_lane(vis)) continue;  // nothing composited here: no gradient, no change of state
      const V t = trans[q];
      const V wi = vis ? alpha * t : zero;
      const V pre = prefix[q] + wi * hp;
      prefix[q] = pre;
      const V g_alpha = t * hp - (total[q] - pre) * reciprocal(one - alpha);
      const V g_pow = (vis & unclamped) ? g_alpha * alpha : zero;
      trans[q] = vis ? t * (one - alpha) : t;
      sums[0] += g_pow * (a * dx + b * dy);
      sums[1] += g_pow * (b * dx + c * dy);
      sums[2] += g_pow * dx * dx;
      sums[3] += g_pow * dx * dy;
      sums[4] += g_pow * dy * dy;
      sums[5] += g_pow;
      for (int64_t ch = 0; ch < nc; ++ch) sf[ch] += wi * g[ch * NCH + q];
    }
    fold_add<scalar_t>(sums, n_k, per + static_cast<int64_t>(id) * groups);
  }
}

// Forward of every tile: colour [C, H, W, D], depth and alpha [C, H, W] (every pixel written),
// stops [C * T * P]; the packed records, rows, order and tile lists are returned for the backward.
template <typename scalar_t, int TS, int NC>
void forward_all(const Inputs<scalar_t>& in, const Rules& rules, int threads, scalar_t* colour, scalar_t* depth,
                 scalar_t* alpha, int32_t* stops, std::vector<int32_t>& order, std::vector<scalar_t>& records,
                 std::vector<int32_t>& rows, std::vector<int64_t>& offsets, std::vector<int32_t>& ids,
                 std::vector<uint8_t>& used) {
  typedef VecOf<scalar_t> V;
  constexpr int L = Simd<scalar_t>::L, P = TS * TS, NCH = P / L;
  pack_and_bin<scalar_t>(in, TS, rules, threads, order, records, rows, offsets, ids);
  const Packed<scalar_t> s{in.n_feat, in.width, in.height, (in.width + TS - 1) / TS, (in.height + TS - 1) / TS,
                           records.data(), rows.data()};
  used.assign(ids.size(), 0);
  const int64_t n_tiles = static_cast<int64_t>(s.tiles_x) * s.tiles_y, d = in.n_feat, n_ch = d + 2;
  const int width = in.width, height = in.height;
#pragma omp parallel num_threads(threads)
  {
    std::vector<V> acc_buf(n_ch * NCH);
    V* acc = acc_buf.data();
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < in.n_cams * n_tiles; ++t) {
      const int64_t c = t / n_tiles, local = t % n_tiles;
      const int tx = static_cast<int>(local % s.tiles_x), ty = static_cast<int>(local / s.tiles_x);
      composite_tile<scalar_t, TS, NC>(s, ids.data() + offsets[t], static_cast<int32_t>(offsets[t + 1] - offsets[t]),
                                       tx, ty, rules, acc, stops + t * P, used.data() + offsets[t]);
      for (int p = 0; p < P; ++p) {
        const int x = tx * TS + p % TS, y = ty * TS + p / TS;
        if (x >= width || y >= height) continue;
        const int64_t pix = (c * height + y) * width + x, q = p / L, l = p % L;
        for (int64_t ch = 0; ch < d; ++ch) colour[pix * d + ch] = acc[ch * NCH + q][l];
        depth[pix] = acc[d * NCH + q][l];
        alpha[pix] = acc[(d + 1) * NCH + q][l];
      }
    }
  }
}

// Backward of every tile into per-thread, per-record sums (tiles dealt to threads round robin, so
// the sums do not depend on timing), then summed per Gaussian. Outputs (zero-filled by the
// caller): g_means2d [C, N, 2], g_conics [C, N, 3], g_depths [C, N], g_opacities [N], g_features
// (shape of the features).
template <typename scalar_t, int TS, int NC>
void backward_all(const Inputs<scalar_t>& in, const Rules& rules, int threads, const Packed<scalar_t>& s,
                  const int32_t* order, int64_t m, const int64_t* offsets, const int32_t* ids, const uint8_t* used,
                  const int32_t* stops, const scalar_t* const outs[3], const scalar_t* const grad_outs[3],
                  scalar_t* gm, scalar_t* gc, scalar_t* gd, scalar_t* go, scalar_t* gf) {
  typedef VecOf<scalar_t> V;
  constexpr int L = Simd<scalar_t>::L, P = TS * TS, NCH = P / L;
  const int64_t n_tiles = static_cast<int64_t>(s.tiles_x) * s.tiles_y, d = in.n_feat, n_ch = d + 2;
  const int64_t n_k = kHead + d + 1;
  const int width = in.width, height = in.height;
  threads = std::max(1, std::min<int>(threads, static_cast<int>(std::min<int64_t>(in.n_cams * n_tiles, 1 << 20))));
  const int64_t groups = (n_k + L - 1) / L;  // vectors per record in the sums
  std::vector<std::vector<V>> per_thread(threads);
#pragma omp parallel num_threads(threads)
  {
#ifdef _OPENMP
    const int me = omp_get_thread_num();
#else
    const int me = 0;
#endif
    std::vector<V>& per = per_thread[me];
    per.assign(std::max<int64_t>(m * groups, 1), V{});
    std::vector<V> g(n_ch * NCH), total(NCH), scratch(n_k);
#pragma omp for schedule(static, 1)
    for (int64_t t = 0; t < in.n_cams * n_tiles; ++t) {
      const int32_t count = static_cast<int32_t>(offsets[t + 1] - offsets[t]);
      if (count == 0) continue;
      const int64_t c = t / n_tiles, local = t % n_tiles;
      const int tx = static_cast<int>(local % s.tiles_x), ty = static_cast<int>(local / s.tiles_x);
      for (int p = 0; p < P; ++p) {
        const int x = tx * TS + p % TS, y = ty * TS + p / TS, q = p / L, l = p % L;
        total[q][l] = 0;
        if (x >= width || y >= height) {
          for (int64_t ch = 0; ch < n_ch; ++ch) g[ch * NCH + q][l] = 0;
          continue;
        }
        const int64_t pix = (c * height + y) * width + x;
        for (int64_t ch = 0; ch < n_ch; ++ch) {
          // channels: D colours, then depth, then alpha (one value per pixel each)
          const int plane = ch < d ? 0 : static_cast<int>(ch - d + 1);
          const int64_t at = plane == 0 ? pix * d + ch : pix;
          g[ch * NCH + q][l] = grad_outs[plane][at];
          total[q][l] += grad_outs[plane][at] * outs[plane][at];
        }
      }
      backward_tile<scalar_t, TS, NC>(s, ids + offsets[t], count, tx, ty, rules, g.data(), total.data(), stops + t * P,
                                      used + offsets[t], scratch.data(), per.data());
    }
  }
  // sum the threads' buffers (fixed order) and scatter per Gaussian
  V* sum = per_thread[0].data();
  for (int th = 1; th < threads; ++th) {
    if (per_thread[th].empty()) continue;  // OpenMP gave fewer threads
    const V* other = per_thread[th].data();
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int64_t j = 0; j < m * groups; ++j) sum[j] += other[j];
  }
  const int* slot = kFoldSlot<scalar_t>.data();
  for (int64_t r = 0; r < m; ++r) {
    const V* row = &sum[r * groups];
    auto at = [row, slot](int64_t j) { return row[j / L][slot[j % L]]; };
    const int64_t i = order[r], gi = i % in.n;
    gm[2 * i] = at(0);
    gm[2 * i + 1] = at(1);
    gc[3 * i] = scalar_t(-0.5) * at(2);  // power = -(a dx^2 + c dy^2) / 2 - b dx dy
    gc[3 * i + 1] = -at(3);
    gc[3 * i + 2] = scalar_t(-0.5) * at(4);
    go[gi] += at(5);  // d / d log(opacity) for now
    scalar_t* dst = gf + (in.per_camera ? i : gi) * d;
    for (int64_t k = 0; k < d; ++k) dst[k] += at(kHead + k);
    gd[i] = at(kHead + d);
  }
  const scalar_t min_o = static_cast<scalar_t>(rules.min_opacity);
  for (int64_t gi = 0; gi < in.n; ++gi) {
    const scalar_t o = in.opacities[gi];
    go[gi] = o >= min_o ? go[gi] / o : scalar_t(0);
  }
}

// ---------------------------------------------------------------------------------------------
// EWA projection (the rules and expressions of edygs_ns/render/projection.py, gsplat's pinhole
// "classic" projection): per (camera, Gaussian) the screen centre, conic, depth and radius, and
// the closed-form backward to means, quaternions, scales and the world-to-camera matrices.

struct ProjectSettings {
  int width, height;
  double near_plane, far_plane, eps2d;
};

constexpr double kRadiusSigmas = 3.0;     // projection.RADIUS_SIGMAS
constexpr double kMinDiscriminant = 0.01;  // projection.MIN_DISCRIMINANT
constexpr double kFovGuardBand = 0.3;     // projection.FOV_GUARD_BAND
constexpr int64_t kBlock = 1024;  // Gaussians per OpenMP work item in the projection loops

// Every intermediate of one (camera, Gaussian) projection that the backward needs.
template <typename scalar_t>
struct ProjTerms {
  scalar_t x, y, z, inv_z, u_c, v_c, j00, j02, j11, j12;
  int in_range, u_free, v_free, valid;  // 0 or 1
  scalar_t a0[3], a1[3], rot[3][3], quat[4], inv_norm, m[3][3], row0[3], row1[3];
  scalar_t cov_a, cov_b, cov_c, det, inv_det, mx, my;
};

template <typename scalar_t>
inline scalar_t dot3(const scalar_t* a, const scalar_t* b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

// view: world-to-camera [4, 4] row-major; k: [3, 3]; mean [3], quat [4] (wxyz), scale [3].
template <typename scalar_t>
__attribute__((always_inline)) inline void project_one(const scalar_t* view, const scalar_t* k, const scalar_t* mean, const scalar_t* q,
                        const scalar_t* scale, const ProjectSettings& ps, ProjTerms<scalar_t>& t) {
  const scalar_t w_img = ps.width, h_img = ps.height;
  t.x = view[0] * mean[0] + view[1] * mean[1] + view[2] * mean[2] + view[3];
  t.y = view[4] * mean[0] + view[5] * mean[1] + view[6] * mean[2] + view[7];
  t.z = view[8] * mean[0] + view[9] * mean[1] + view[10] * mean[2] + view[11];
  t.in_range = (t.z >= static_cast<scalar_t>(ps.near_plane)) & (t.z <= static_cast<scalar_t>(ps.far_plane));
  const scalar_t z_safe = t.in_range ? t.z : scalar_t(1);
  const scalar_t fx = k[0], fy = k[4], cx = k[2], cy = k[5];
  t.inv_z = scalar_t(1) / z_safe;
  const scalar_t u = t.x * t.inv_z, v = t.y * t.inv_z;
  t.mx = fx * u + cx;
  t.my = fy * v + cy;
  const scalar_t band = static_cast<scalar_t>(kFovGuardBand);
  const scalar_t tan_x = scalar_t(0.5) * w_img / fx, tan_y = scalar_t(0.5) * h_img / fy;
  const scalar_t lim_x_pos = (w_img - cx) / fx + band * tan_x, lim_x_neg = cx / fx + band * tan_x;
  const scalar_t lim_y_pos = (h_img - cy) / fy + band * tan_y, lim_y_neg = cy / fy + band * tan_y;
  t.j00 = fx * t.inv_z;
  t.j11 = fy * t.inv_z;
  t.u_c = std::min(std::max(u, -lim_x_neg), lim_x_pos);
  t.v_c = std::min(std::max(v, -lim_y_neg), lim_y_pos);
  t.j02 = -t.j00 * t.u_c;
  t.j12 = -t.j11 * t.v_c;
  t.u_free = (u >= -lim_x_neg) & (u <= lim_x_pos);
  t.v_free = (v >= -lim_y_neg) & (v <= lim_y_pos);
  for (int j = 0; j < 3; ++j) {
    t.a0[j] = t.j00 * view[j] + t.j02 * view[8 + j];
    t.a1[j] = t.j11 * view[4 + j] + t.j12 * view[8 + j];
  }
  t.inv_norm = scalar_t(1) / std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  for (int j = 0; j < 4; ++j) t.quat[j] = q[j] * t.inv_norm;
  const scalar_t w = t.quat[0], x = t.quat[1], y = t.quat[2], z = t.quat[3];
  const scalar_t xx = x * x, yy = y * y, zz = z * z, xy = x * y, xz = x * z, yz = y * z;
  const scalar_t wx = w * x, wy = w * y, wz = w * z;
  const scalar_t rot[3][3] = {{1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)},
                              {2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)},
                              {2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)}};
  for (int j = 0; j < 3; ++j)
    for (int c = 0; c < 3; ++c) {
      t.rot[j][c] = rot[j][c];
      t.m[j][c] = rot[j][c] * scale[c];
    }
  for (int c = 0; c < 3; ++c) {
    t.row0[c] = t.a0[0] * t.m[0][c] + t.a0[1] * t.m[1][c] + t.a0[2] * t.m[2][c];
    t.row1[c] = t.a1[0] * t.m[0][c] + t.a1[1] * t.m[1][c] + t.a1[2] * t.m[2][c];
  }
  const scalar_t eps = static_cast<scalar_t>(ps.eps2d);
  t.cov_a = dot3(t.row0, t.row0) + eps;
  t.cov_b = dot3(t.row0, t.row1);
  t.cov_c = dot3(t.row1, t.row1) + eps;
  t.det = t.cov_a * t.cov_c - t.cov_b * t.cov_b;
  t.valid = t.in_range & (t.det > 0);
  t.inv_det = scalar_t(1) / (t.valid ? t.det : scalar_t(1));
}

// Outputs: means2d [C, N, 2], conics [C, N, 3], depths [C, N], radii [C, N] (0 = culled).
// Per camera one loop over the Gaussians that the compiler vectorises.
template <typename scalar_t>
void project_forward_all(const scalar_t* means, const scalar_t* quats, const scalar_t* scales, const scalar_t* views,
                         const scalar_t* ks, int64_t n_cams, int64_t n, const ProjectSettings ps, int threads,
                         scalar_t* means2d, scalar_t* conics, scalar_t* depths, int32_t* radii) {
  const scalar_t width = ps.width, height = ps.height;
  for (int64_t c = 0; c < n_cams; ++c) {
#pragma omp parallel num_threads(threads)
  {
    // the camera as thread-private locals (kept in registers; shared ones are re-read per lane)
    scalar_t view[16], k[9];
    std::copy(views + 16 * c, views + 16 * (c + 1), view);
    std::copy(ks + 9 * c, ks + 9 * (c + 1), k);
#pragma omp for schedule(static)
    for (int64_t blk = 0; blk < (n + kBlock - 1) / kBlock; ++blk) {
    const int64_t g_end = std::min(n, (blk + 1) * kBlock);
#pragma GCC ivdep
    for (int64_t g = blk * kBlock; g < g_end; ++g) {
      ProjTerms<scalar_t> t;
      const int64_t i = c * n + g;
      const scalar_t mean[3] = {means[3 * g], means[3 * g + 1], means[3 * g + 2]};
      const scalar_t quat[4] = {quats[4 * g], quats[4 * g + 1], quats[4 * g + 2], quats[4 * g + 3]};
      const scalar_t scale[3] = {scales[3 * g], scales[3 * g + 1], scales[3 * g + 2]};
      project_one(view, k, mean, quat, scale, ps, t);
      means2d[2 * i] = t.mx;
      means2d[2 * i + 1] = t.my;
      conics[3 * i] = t.cov_c * t.inv_det;
      conics[3 * i + 1] = -t.cov_b * t.inv_det;
      conics[3 * i + 2] = t.cov_a * t.inv_det;
      depths[i] = t.z;
      const scalar_t half_trace = scalar_t(0.5) * (t.cov_a + t.cov_c);
      const scalar_t major =
          half_trace + std::sqrt(std::max(half_trace * half_trace - t.det, static_cast<scalar_t>(kMinDiscriminant)));
      const scalar_t radius = std::ceil(static_cast<scalar_t>(kRadiusSigmas) * std::sqrt(major));
      const bool on_screen = (t.mx + radius > 0) & (t.mx - radius < width) & (t.my + radius > 0) &
                             (t.my - radius < height);
      radii[i] = (t.valid & on_screen & (radius > 0)) ? static_cast<int32_t>(radius) : 0;
    }
    }
  }
  }
}

// Gradients: g_means [N, 3], g_quats [N, 4], g_scales [N, 3] (overwritten), g_views [C, 4, 4]
// (zero-filled by the caller; rows 0-2 written). Per camera one vectorised loop over the
// Gaussians adds into per-Gaussian sums of dL/dM and dL/d(mean) (scratch, one row per entry) and
// writes each Gaussian's twelve view-matrix terms (scratch rows), summed afterwards in double; then
// one loop turns dL/dM into scales and quaternions.
template <typename scalar_t>
void project_backward_all(const scalar_t* means, const scalar_t* quats, const scalar_t* scales, const scalar_t* views,
                          const scalar_t* ks, int64_t n_cams, int64_t n, const ProjectSettings ps, int threads,
                          const scalar_t* g_means2d, const scalar_t* g_conics, const scalar_t* g_depths,
                          scalar_t* g_means, scalar_t* g_quats, scalar_t* g_scales, scalar_t* g_views) {
  std::vector<scalar_t> scratch(24 * std::max<int64_t>(n, 1), scalar_t(0));
  scalar_t* gm_rows = scratch.data();    // [9, N] dL/dM (M = R diag(s)), row 3 j + k
  scalar_t* gp_rows = gm_rows + 9 * n;   // [3, N] dL/d(mean)
  scalar_t* vt_rows = gm_rows + 12 * n;  // [12, N] this camera's view-matrix terms, row 4 r + j
  for (int64_t c = 0; c < n_cams; ++c) {
#pragma omp parallel num_threads(threads)
  {
    scalar_t view[16], k[9];  // thread-private copies (kept in registers)
    std::copy(views + 16 * c, views + 16 * (c + 1), view);
    std::copy(ks + 9 * c, ks + 9 * (c + 1), k);
    const scalar_t fx = k[0], fy = k[4];
    const scalar_t* r0 = view;
    const scalar_t* r1 = view + 4;
    const scalar_t* r2 = view + 8;
#pragma omp for schedule(static)
    for (int64_t blk = 0; blk < (n + kBlock - 1) / kBlock; ++blk) {
    const int64_t g_end = std::min(n, (blk + 1) * kBlock);
#pragma GCC ivdep
    for (int64_t g = blk * kBlock; g < g_end; ++g) {
      ProjTerms<scalar_t> t;
      const int64_t i = c * n + g;
      const scalar_t mean[3] = {means[3 * g], means[3 * g + 1], means[3 * g + 2]};
      const scalar_t quat[4] = {quats[4 * g], quats[4 * g + 1], quats[4 * g + 2], quats[4 * g + 3]};
      const scalar_t scale[3] = {scales[3 * g], scales[3 * g + 1], scales[3 * g + 2]};
      project_one(view, k, mean, quat, scale, ps, t);
      // conics = (c, -b, a) / det  (det frozen to 1 where invalid)
      const scalar_t gc0 = g_conics[3 * i], gc1 = g_conics[3 * i + 1], gc2 = g_conics[3 * i + 2];
      const scalar_t inv_det = t.inv_det;
      scalar_t s = (gc0 * t.cov_c - gc1 * t.cov_b + gc2 * t.cov_a) * inv_det * inv_det;
      s = t.valid ? s : scalar_t(0);
      const scalar_t g_a = gc2 * inv_det - s * t.cov_c;
      const scalar_t g_c = gc0 * inv_det - s * t.cov_a;
      const scalar_t g_b = 2 * s * t.cov_b - gc1 * inv_det;
      // cov = (A M)(A M)^T
      scalar_t g_row0[3], g_row1[3], g_a0[3], g_a1[3];
      for (int q = 0; q < 3; ++q) {
        g_row0[q] = 2 * g_a * t.row0[q] + g_b * t.row1[q];
        g_row1[q] = 2 * g_c * t.row1[q] + g_b * t.row0[q];
      }
      for (int j = 0; j < 3; ++j) {
        g_a0[j] = dot3(g_row0, t.m[j]);
        g_a1[j] = dot3(g_row1, t.m[j]);
        for (int q = 0; q < 3; ++q) gm_rows[(3 * j + q) * n + g] += t.a0[j] * g_row0[q] + t.a1[j] * g_row1[q];
      }
      // A = J R_view
      const scalar_t g_j00 = dot3(g_a0, r0), g_j02 = dot3(g_a0, r2);
      const scalar_t g_j11 = dot3(g_a1, r1), g_j12 = dot3(g_a1, r2);
      // J: j00 = fx / z, j02 = -j00 clamp(u), j11 = fy / z, j12 = -j11 clamp(v)
      scalar_t g_inv_z = fx * (g_j00 - g_j02 * t.u_c) + fy * (g_j11 - g_j12 * t.v_c);
      const scalar_t g_u = (t.u_free ? -g_j02 * t.j00 : scalar_t(0)) + fx * g_means2d[2 * i];
      const scalar_t g_v = (t.v_free ? -g_j12 * t.j11 : scalar_t(0)) + fy * g_means2d[2 * i + 1];
      const scalar_t g_x = g_u * t.inv_z, g_y = g_v * t.inv_z;
      g_inv_z += g_u * t.x + g_v * t.y;
      const scalar_t g_z = (t.in_range ? -g_inv_z * t.inv_z * t.inv_z : scalar_t(0)) + g_depths[i];
      // camera position p = R_view m + t
      for (int j = 0; j < 3; ++j) gp_rows[j * n + g] += g_x * r0[j] + g_y * r1[j] + g_z * r2[j];
      for (int j = 0; j < 3; ++j) {
        vt_rows[j * n + g] = g_a0[j] * t.j00 + g_x * mean[j];
        vt_rows[(4 + j) * n + g] = g_a1[j] * t.j11 + g_y * mean[j];
        vt_rows[(8 + j) * n + g] = g_a0[j] * t.j02 + g_a1[j] * t.j12 + g_z * mean[j];
      }
      vt_rows[3 * n + g] = g_x;
      vt_rows[7 * n + g] = g_y;
      vt_rows[11 * n + g] = g_z;
    }
    }
  }
#pragma omp parallel for schedule(static) num_threads(threads)
    for (int j = 0; j < 12; ++j) {
      const scalar_t* row = vt_rows + j * n;
      double sum = 0;
      for (int64_t g = 0; g < n; ++g) sum += row[g];
      g_views[16 * c + j] = static_cast<scalar_t>(sum);
    }
  }
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t blk = 0; blk < (n + kBlock - 1) / kBlock; ++blk) {
  const int64_t g_end = std::min(n, (blk + 1) * kBlock);
#pragma GCC ivdep
  for (int64_t g = blk * kBlock; g < g_end; ++g) {
    const scalar_t* q = quats + 4 * g;
    const scalar_t inv_norm = scalar_t(1) / std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    const scalar_t w = q[0] * inv_norm, x = q[1] * inv_norm, y = q[2] * inv_norm, z = q[3] * inv_norm;
    const scalar_t xx = x * x, yy = y * y, zz = z * z, xy = x * y, xz = x * z, yz = y * z;
    const scalar_t wx = w * x, wy = w * y, wz = w * z;
    const scalar_t rot[3][3] = {{1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)},
                                {2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)},
                                {2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)}};
    const scalar_t* scale = scales + 3 * g;
    scalar_t g_r[3][3];
    for (int kk = 0; kk < 3; ++kk) {
      scalar_t acc = 0;
      for (int j = 0; j < 3; ++j) {
        const scalar_t gmjk = gm_rows[(3 * j + kk) * n + g];
        acc += gmjk * rot[j][kk];
        g_r[j][kk] = gmjk * scale[kk];
      }
      g_scales[3 * g + kk] = acc;
    }
    for (int j = 0; j < 3; ++j) g_means[3 * g + j] = gp_rows[j * n + g];
    const scalar_t s01 = g_r[0][1] + g_r[1][0], s02 = g_r[0][2] + g_r[2][0], s12 = g_r[1][2] + g_r[2][1];
    const scalar_t a10 = g_r[1][0] - g_r[0][1], a02 = g_r[0][2] - g_r[2][0], a21 = g_r[2][1] - g_r[1][2];
    const scalar_t gw = 2 * (z * a10 + y * a02 + x * a21);
    const scalar_t gx = 2 * (y * s01 + z * s02 + w * a21) - 4 * x * (g_r[1][1] + g_r[2][2]);
    const scalar_t gy = 2 * (x * s01 + w * a02 + z * s12) - 4 * y * (g_r[0][0] + g_r[2][2]);
    const scalar_t gz = 2 * (w * a10 + x * s02 + y * s12) - 4 * z * (g_r[0][0] + g_r[1][1]);
    // q_hat = q / |q|: the gradient loses its radial part
    const scalar_t radial = w * gw + x * gx + y * gy + z * gz;
    g_quats[4 * g] = (gw - w * radial) * inv_norm;
    g_quats[4 * g + 1] = (gx - x * radial) * inv_norm;
    g_quats[4 * g + 2] = (gy - y * radial) * inv_norm;
    g_quats[4 * g + 3] = (gz - z * radial) * inv_norm;
  }
  }
}

}  // namespace

#ifdef RASTER_KERNELS_ONLY
// Standalone build of the kernels (vectorisation reports, no torch headers).
__attribute__((used)) void kernels_float8(const Inputs<float>& in, const Rules& rules, float* out, int32_t* stops,
                                          std::vector<int32_t>& order, std::vector<float>& records,
                                          std::vector<int32_t>& rows, std::vector<int64_t>& offsets,
                                          std::vector<int32_t>& ids, std::vector<uint8_t>& used, float* g) {
  forward_all<float, 8, 5>(in, rules, 1, out, out, out, stops, order, records, rows, offsets, ids, used);
  const float* const three[3] = {out, out, out};
  const Packed<float> s{in.n_feat, in.width, in.height, (in.width + 7) / 8, (in.height + 7) / 8, records.data(),
                        rows.data()};
  backward_all<float, 8, 5>(in, rules, 1, s, order.data(), static_cast<int64_t>(order.size()), offsets.data(),
                            ids.data(), used.data(), stops, three, three, g, g, g, g, g);
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

template <typename T>
at::Tensor tensor_of(const std::vector<T>& v, int64_t n, at::ScalarType type) {
  at::Tensor out = at::empty({n}, at::TensorOptions().dtype(type));
  if (n > 0) std::memcpy(out.data_ptr(), v.data(), n * sizeof(T));
  return out;
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
    std::vector<int32_t> order, rows, ids;
    std::vector<scalar_t> records;
    std::vector<int64_t> offsets;
    std::vector<uint8_t> used;
    forward_all<scalar_t, TS, NC>(in, r, at::get_num_threads(), colour.data_ptr<scalar_t>(), depth.data_ptr<scalar_t>(),
                                  alpha.data_ptr<scalar_t>(), stops.data_ptr<int32_t>(), order, records, rows, offsets,
                                  ids, used);
    const int64_t m = static_cast<int64_t>(order.size()), stride = kHead + in.n_feat + 1;
    at::Tensor records_t = at::empty({m, stride}, means2d.options());
    if (m > 0) std::memcpy(records_t.data_ptr<scalar_t>(), records.data(), m * stride * sizeof(scalar_t));
    return std::vector<at::Tensor>{colour, depth, alpha,
                                   tensor_of(offsets, static_cast<int64_t>(offsets.size()), at::kLong),
                                   tensor_of(ids, static_cast<int64_t>(ids.size()), at::kInt),
                                   tensor_of(used, static_cast<int64_t>(used.size()), at::kByte), stops,
                                   tensor_of(order, m, at::kInt), records_t, tensor_of(rows, 2 * m, at::kInt)};
  });
}

std::vector<at::Tensor> rasterize_backward(const at::Tensor& means2d, const at::Tensor& conics,
                                           const at::Tensor& opacities, const at::Tensor& features,
                                           const at::Tensor& depths, const at::Tensor& radii, int64_t width,
                                           int64_t height, int64_t tile, const std::vector<double>& rules,
                                           const std::vector<at::Tensor>& saved, const std::vector<at::Tensor>& outs,
                                           const std::vector<at::Tensor>& grad_outs) {
  TORCH_CHECK(outs.size() == 3 && grad_outs.size() == 3, "raster_cpu: colour, depth and alpha and their gradients");
  for (int i = 0; i < 3; ++i) {
    TORCH_CHECK(grad_outs[i].is_contiguous() && outs[i].is_contiguous() && grad_outs[i].sizes() == outs[i].sizes(),
                "raster_cpu: each gradient must be contiguous and match its output");
  }
  TORCH_CHECK(saved.size() == 7, "raster_cpu: the forward's offsets, ids, used, stops, order, records and rows");
  const at::Tensor &offsets = saved[0], &ids = saved[1], &used = saved[2], &stops = saved[3], &order = saved[4],
                   &records = saved[5], &rows = saved[6];
  TORCH_CHECK(used.scalar_type() == at::kByte && used.numel() == ids.numel(), "raster_cpu: used must match ids");
  const Rules r = rules_from(rules);
  return dispatch(means2d, tile, features.size(-1), [&](auto scalar, auto ts, auto nc) {
    using scalar_t = decltype(scalar);
    constexpr int TS = decltype(ts)::value, NC = decltype(nc)::value;
    const Inputs<scalar_t> in = inputs_of<scalar_t>(means2d, conics, opacities, features, depths, radii, width, height);
    TORCH_CHECK(records.scalar_type() == means2d.scalar_type() && records.is_contiguous() &&
                    records.size(0) == order.numel() && records.size(1) == kHead + in.n_feat + 1,
                "raster_cpu: the saved records do not match the inputs");
    at::Tensor g_means2d = at::zeros_like(means2d), g_conics = at::zeros_like(conics);
    at::Tensor g_depths = at::zeros_like(depths), g_opacities = at::zeros_like(opacities);
    at::Tensor g_features = at::zeros_like(features);
    const scalar_t* const out_p[3] = {outs[0].data_ptr<scalar_t>(), outs[1].data_ptr<scalar_t>(),
                                      outs[2].data_ptr<scalar_t>()};
    const scalar_t* const grad_p[3] = {grad_outs[0].data_ptr<scalar_t>(), grad_outs[1].data_ptr<scalar_t>(),
                                       grad_outs[2].data_ptr<scalar_t>()};
    const Packed<scalar_t> s{in.n_feat, in.width, in.height, static_cast<int>((width + TS - 1) / TS),
                             static_cast<int>((height + TS - 1) / TS), records.data_ptr<scalar_t>(),
                             rows.data_ptr<int32_t>()};
    backward_all<scalar_t, TS, NC>(in, r, at::get_num_threads(), s, order.data_ptr<int32_t>(), order.numel(),
                                   offsets.data_ptr<int64_t>(), ids.data_ptr<int32_t>(), used.data_ptr<uint8_t>(),
                                   stops.data_ptr<int32_t>(), out_p, grad_p, g_means2d.data_ptr<scalar_t>(),
                                   g_conics.data_ptr<scalar_t>(), g_depths.data_ptr<scalar_t>(),
                                   g_opacities.data_ptr<scalar_t>(), g_features.data_ptr<scalar_t>());
    return std::vector<at::Tensor>{g_means2d, g_conics, g_opacities, g_features, g_depths};
  });
}

namespace {

ProjectSettings project_settings(const std::vector<double>& v) {
  TORCH_CHECK(v.size() == 5, "raster_cpu: projection settings are width, height, near, far, eps2d");
  return ProjectSettings{static_cast<int>(v[0]), static_cast<int>(v[1]), v[2], v[3], v[4]};
}

void check_projection_inputs(const at::Tensor& means, const std::vector<at::Tensor>& others) {
  TORCH_CHECK(means.device().is_cpu() && means.is_contiguous(), "raster_cpu: means must be a contiguous CPU tensor");
  TORCH_CHECK(means.scalar_type() == at::kFloat || means.scalar_type() == at::kDouble,
              "raster_cpu: float32 or float64 only, got ", means.scalar_type());
  for (const at::Tensor& t : others)
    TORCH_CHECK(t.device().is_cpu() && t.is_contiguous() && t.scalar_type() == means.scalar_type(),
                "raster_cpu: projection inputs must be contiguous CPU tensors of one dtype");
}

}  // namespace

// means [N, 3], quats [N, 4], scales [N, 3], viewmats [C, 4, 4], Ks [C, 3, 3]; settings: width,
// height, near, far, eps2d. Returns means2d [C, N, 2], conics [C, N, 3], depths [C, N], radii [C, N].
std::vector<at::Tensor> project_forward(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                        const at::Tensor& viewmats, const at::Tensor& ks,
                                        const std::vector<double>& settings) {
  check_projection_inputs(means, {quats, scales, viewmats, ks});
  const ProjectSettings ps = project_settings(settings);
  const int64_t n = means.size(0), n_cams = viewmats.size(0);
  TORCH_CHECK(n_cams > 0, "raster_cpu: at least one camera");
  at::Tensor means2d = at::empty({n_cams, n, 2}, means.options());
  at::Tensor conics = at::empty({n_cams, n, 3}, means.options());
  at::Tensor depths = at::empty({n_cams, n}, means.options());
  at::Tensor radii = at::empty({n_cams, n}, means.options().dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
    project_forward_all<scalar_t>(means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
                                  viewmats.data_ptr<scalar_t>(), ks.data_ptr<scalar_t>(), n_cams, n, ps,
                                  at::get_num_threads(), means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                                  depths.data_ptr<scalar_t>(), radii.data_ptr<int32_t>());
  });
  return {means2d, conics, depths, radii};
}

// Gradients of project_forward's means2d, conics and depths to means, quats, scales and viewmats.
std::vector<at::Tensor> project_backward(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                         const at::Tensor& viewmats, const at::Tensor& ks,
                                         const std::vector<double>& settings, const at::Tensor& g_means2d,
                                         const at::Tensor& g_conics, const at::Tensor& g_depths) {
  check_projection_inputs(means, {quats, scales, viewmats, ks, g_means2d, g_conics, g_depths});
  const ProjectSettings ps = project_settings(settings);
  const int64_t n = means.size(0), n_cams = viewmats.size(0);
  TORCH_CHECK(n_cams > 0, "raster_cpu: at least one camera");
  at::Tensor g_means = at::empty_like(means), g_quats = at::empty_like(quats), g_scales = at::empty_like(scales);
  at::Tensor g_views = at::zeros_like(viewmats);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    project_backward_all<scalar_t>(
        means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(),
        viewmats.data_ptr<scalar_t>(), ks.data_ptr<scalar_t>(), n_cams, n, ps, at::get_num_threads(),
        g_means2d.data_ptr<scalar_t>(), g_conics.data_ptr<scalar_t>(), g_depths.data_ptr<scalar_t>(),
        g_means.data_ptr<scalar_t>(), g_quats.data_ptr<scalar_t>(), g_scales.data_ptr<scalar_t>(),
        g_views.data_ptr<scalar_t>());
  });
  return {g_means, g_quats, g_scales, g_views};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &rasterize_forward, "tile binning and compositing (CPU)");
  m.def("backward", &rasterize_backward, "gradients of rasterize_forward's first output (CPU)");
  m.def("project_forward", &project_forward, "EWA projection of 3D Gaussians (CPU)");
  m.def("project_backward", &project_backward, "gradients of project_forward (CPU)");
}

#endif  // RASTER_KERNELS_ONLY
