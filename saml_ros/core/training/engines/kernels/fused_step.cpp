// The fused training kernel of saml_ros (saml_ros/core/training/engines/fused.py): a block of primal-dual steps
// of an EnsembleMLP ensemble (gather, forward, spec values, closed-form loss gradient, backward, Adam / SGD of the
// primal flat tensor, dual update of the multipliers) in one call, without per-operation torch dispatch.
//
// The arithmetic is the fast engine's (saml_ros/core/training/engines/fast.py, flat.py, closed_form.py, dual.py,
// nupi.py) operation by operation; only summation orders differ (plain loops instead of bmm). Layouts are the
// fast engine's FlatNet: layer i is (E, d_in + 1, d_out) with the bias as last row, then the PReLU slopes
// (L - 1, E), then n_extra merged dual slots per member (E, n_extra).
//
// Inner loops run over contiguous memory with no branches, so g++ -O3 -march=native vectorises them.
#include <ATen/core/Tensor.h>
#include <torch/csrc/utils/pybind.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

namespace {

enum Loss : int64_t { L2 = 0, SQUARED_L2 = 1, L1 = 2, HUBER = 3, NORMALIZED = 4 };
enum OptKind : int64_t { ADAM = 0, SGD = 1 };
// how the multipliers move: none (no constraint), Adam merged into the primal flat tensor, own Adam, own SGD, nuPI
enum DualOpt : int64_t { D_NONE = 0, D_MERGED = 1, D_ADAM = 2, D_SGD = 3, D_NUPI = 4 };
// which dual method's arithmetic: the paper's, nuPI, augmented Lagrangian, resilient
enum DualMethod : int64_t { M_PAPER = 0, M_NUPI = 1, M_AUGMENTED = 2, M_RESILIENT = 3 };

// the native vector width -march=native gives (the matmul's register blocks are two such vectors wide)
#if defined(__AVX512F__)
constexpr int64_t VEC_BYTES = 64;
#elif defined(__AVX__)
constexpr int64_t VEC_BYTES = 32;
#else
constexpr int64_t VEC_BYTES = 16;
#endif

// a loop over the fields of term j: 0..NY-1 directly when the term takes every field (a contiguous loop the
// compiler vectorises), else through the term's field indices
#define FOR_FIELDS(j, f, ...)                                   \
  if (all_fields_[j]) {                                         \
    _Pragma("GCC ivdep") for (int64_t f = 0; f < NY; ++f) {     \
      __VA_ARGS__                                               \
    }                                                           \
  } else {                                                      \
    for (int64_t f : fields_[j]) {                              \
      __VA_ARGS__                                               \
    }                                                           \
  }

constexpr double TINY = 1e-30;   // closed_form._TINY
constexpr double F_MIN = 1e-12;  // ResilientDual.F_MIN

template <typename T>
inline T lerp_(T a, T b, T w) {
  // at::lerp's formula (aten/src/ATen/native/Lerp.h)
  return (std::abs(w) < T(0.5)) ? a + w * (b - a) : b - (b - a) * (T(1) - w);
}

class FusedKernel {
 public:
  // tensors: flat, grad, m, v, lam, dm, dv, xi, src_z, src_r, src_mask, src_ny, ostd, counts
  // ints: E, B, n, L, dims[L+1], T, n_y, per_member, z_per_member, popt, dual_opt, dual_method, n_extra,
  //       then per term: loss, conditional, n_fields, fields...
  // dbls: popt b1, b2, eps; dual b1, b2, eps; k_dual; kp; nu; then per term: eps, delta; then per constraint:
  //       rho, eps2, dual eps
  FusedKernel(std::vector<at::Tensor> tensors, std::vector<int64_t> ints, std::vector<double> dbls)
      : ts_(std::move(tensors)) {
    size_t p = 0;
    E_ = ints[p++];
    B_ = ints[p++];
    n_ = ints[p++];
    L_ = ints[p++];
    for (int64_t i = 0; i <= L_; ++i) dims_.push_back(ints[p++]);
    T_ = ints[p++];
    K_ = T_ - 1;
    ny_ = ints[p++];
    per_member_ = ints[p++] != 0;
    z_per_member_ = ints[p++] != 0;
    popt_ = ints[p++];
    dopt_ = ints[p++];
    method_ = ints[p++];
    n_extra_ = ints[p++];
    for (int64_t j = 0; j < T_; ++j) {
      loss_.push_back(ints[p++]);
      cond_.push_back(ints[p++] != 0);
      int64_t nf = ints[p++];
      std::vector<int64_t> f;
      for (int64_t k = 0; k < nf; ++k) f.push_back(ints[p++]);
      bool all = int64_t(f.size()) == ny_;
      for (int64_t k = 0; all && k < nf; ++k) all = f[k] == k;
      all_fields_.push_back(all);
      fields_.push_back(f);
    }
    size_t q = 0;
    b1_ = dbls[q++];
    b2_ = dbls[q++];
    peps_ = dbls[q++];
    db1_ = dbls[q++];
    db2_ = dbls[q++];
    deps_ = dbls[q++];
    k_dual_ = dbls[q++];
    kp_ = dbls[q++];
    nu_ = dbls[q++];
    for (int64_t j = 0; j < T_; ++j) {
      teps_.push_back(dbls[q++]);
      delta_.push_back(dbls[q++]);
    }
    for (int64_t k = 0; k < K_; ++k) {
      rho_.push_back(dbls[q++]);
      eps2_.push_back(dbls[q++]);
      deps_k_.push_back(dbls[q++]);
    }
    // flat layout
    int64_t off = 0;
    for (int64_t i = 0; i < L_; ++i) {
      w_off_.push_back(off);
      off += E_ * (dims_[i] + 1) * dims_[i + 1];
    }
    s_off_ = off;
    off += E_ * (L_ - 1);
    x_off_ = off;
    off += E_ * n_extra_;
    P_ = off;
    TORCH_CHECK(ts_[0].numel() == P_, "fused kernel: flat tensor size ", ts_[0].numel(), " != ", P_);
    for (auto& t : ts_) {
      TORCH_CHECK(!t.defined() || t.numel() == 0 || t.device().is_cpu(), "fused kernel: CPU tensors only");
    }
    is_double_ = ts_[0].scalar_type() == at::kDouble;
    TORCH_CHECK(is_double_ || ts_[0].scalar_type() == at::kFloat, "fused kernel: float32 or float64 only");
    max_d_ = *std::max_element(dims_.begin(), dims_.end()) + 1;
  }

  // the minibatch indices (S, E, B) int64, the values out (S, E, T), the per-step learning rates (S, 2) float64
  void set_chunk(at::Tensor idx, at::Tensor vals, at::Tensor lrs) {
    TORCH_CHECK(idx.is_contiguous() && idx.scalar_type() == at::kLong && idx.dim() == 3, "fused kernel: idx");
    TORCH_CHECK(idx.size(1) == E_ && idx.size(2) == B_, "fused kernel: idx shape");
    TORCH_CHECK(vals.is_contiguous() && vals.size(0) == idx.size(0), "fused kernel: vals");
    TORCH_CHECK(lrs.is_contiguous() && lrs.scalar_type() == at::kDouble && lrs.size(0) == idx.size(0),
                "fused kernel: lrs");
    idx_ = idx;
    vals_ = vals;
    lrs_ = lrs;
  }

  // steps s0..s1-1 of the chunk; stats (float64, 3): worst and mean over those steps of the members' summed
  // objective, then the largest |value| of the flat parameters and lambda after them (NaN if any is NaN)
  void run(int64_t s0, int64_t s1, at::Tensor stats) {
    if (is_double_) {
      run_impl<double>(s0, s1, stats);
    } else {
      run_impl<float>(s0, s1, stats);
    }
  }

  // dataset-level spec sums at the current parameters: sums[e, j] = sum over member e's n samples of term j's
  // per-sample loss times its region mask, counts[e, j] = the denominator's count (the mask's sum for a conditional
  // term, n otherwise); both float64 (E, T), as saml_ros.core.training.evaluate.evaluate_spec accumulates them
  void evaluate(at::Tensor sums, at::Tensor counts) {
    TORCH_CHECK(sums.is_contiguous() && counts.is_contiguous() && sums.scalar_type() == at::kDouble &&
                counts.scalar_type() == at::kDouble && sums.numel() == E_ * T_ && counts.numel() == E_ * T_,
                "fused kernel: evaluate buffers");
    if (is_double_) {
      evaluate_impl<double>(sums.data_ptr<double>(), counts.data_ptr<double>());
    } else {
      evaluate_impl<float>(sums.data_ptr<double>(), counts.data_ptr<double>());
    }
  }

  // copy the state the steps change (flat, moments, lambda, xi, counters) into the snapshot / back
  void snapshot() { copy_state(true); }
  void restore() { copy_state(false); }

 private:
  std::vector<at::Tensor> ts_;
  at::Tensor idx_, vals_, lrs_;
  std::vector<at::Tensor> snap_;
  std::vector<int64_t> snap_counts_;
  int64_t E_, B_, n_, L_, T_, K_, ny_, popt_, dopt_, method_, n_extra_;
  bool per_member_, z_per_member_, is_double_;
  std::vector<int64_t> dims_, loss_, w_off_;
  std::vector<bool> cond_, all_fields_;
  std::vector<std::vector<int64_t>> fields_;
  double b1_, b2_, peps_, db1_, db2_, deps_, k_dual_, kp_, nu_;
  std::vector<double> teps_, delta_, rho_, eps2_, deps_k_;
  int64_t s_off_, x_off_, P_, max_d_;
  // scratch
  std::vector<double> scratch_d_;
  std::vector<float> scratch_f_;

  enum { FLAT = 0, GRAD, M, V, LAM, DM, DV, XI, SRC_Z, SRC_R, SRC_MASK, SRC_NY, OSTD, COUNTS };

  void copy_state(bool save) {
    const int ids[] = {FLAT, M, V, DM, DV, XI};
    if (save && snap_.empty()) {
      for (int i : ids) snap_.push_back(ts_[i].numel() ? ts_[i].clone() : at::Tensor());
      snap_.push_back(ts_[LAM].clone());
    }
    size_t k = 0;
    for (int i : ids) {
      if (ts_[i].numel()) {
        if (save) snap_[k].copy_(ts_[i]); else ts_[i].copy_(snap_[k]);
      }
      ++k;
    }
    if (save) snap_[k].copy_(ts_[LAM]); else ts_[LAM].copy_(snap_[k]);
    auto* c = ts_[COUNTS].data_ptr<int64_t>();
    if (save) {
      snap_counts_.assign(c, c + 4);
    } else {
      std::copy(snap_counts_.begin(), snap_counts_.end(), c);
    }
  }

  template <typename S>
  S* ptr(int i) {
    return ts_[i].numel() ? ts_[i].data_ptr<S>() : nullptr;
  }

  // C (rows x np, row stride ldc) = A (rows x k; element (r, kk) at A[r * rs + kk * cs]) * Wp (k x np, padded
  // with zeros to whole native vectors of S). Register blocking: 4 rows x 2 vectors of C (or 8 rows x 1 vector for
  // the last columns) stay in eight vector accumulators (GCC vector extensions, the target's native width).
  template <typename S>
  static void gemm(int64_t rows, int64_t k, const S* A, int64_t rs, int64_t cs, const S* Wp, int64_t np, S* C,
                   int64_t ldc) {
    typedef S V __attribute__((vector_size(VEC_BYTES), aligned(sizeof(S))));
    constexpr int64_t W1 = VEC_BYTES / sizeof(S);  // one vector
    int64_t j0 = 0;
    for (; j0 + 2 * W1 <= np; j0 += 2 * W1) {
      int64_t r = 0;
      for (; r + 4 <= rows; r += 4) {
        V c00 = {}, c01 = {}, c10 = {}, c11 = {}, c20 = {}, c21 = {}, c30 = {}, c31 = {};
        const S* a0 = A + r * rs;
        const S* a1 = a0 + rs;
        const S* a2 = a1 + rs;
        const S* a3 = a2 + rs;
        const S* w = Wp + j0;
        for (int64_t kk = 0; kk < k; ++kk, w += np) {
          const V w0 = *reinterpret_cast<const V*>(w);
          const V w1 = *reinterpret_cast<const V*>(w + W1);
          const int64_t o = kk * cs;
          const S x0 = a0[o], x1 = a1[o], x2 = a2[o], x3 = a3[o];
          c00 += x0 * w0;
          c01 += x0 * w1;
          c10 += x1 * w0;
          c11 += x1 * w1;
          c20 += x2 * w0;
          c21 += x2 * w1;
          c30 += x3 * w0;
          c31 += x3 * w1;
        }
        S* o0 = C + r * ldc + j0;
        *reinterpret_cast<V*>(o0) = c00;
        *reinterpret_cast<V*>(o0 + W1) = c01;
        *reinterpret_cast<V*>(o0 + ldc) = c10;
        *reinterpret_cast<V*>(o0 + ldc + W1) = c11;
        *reinterpret_cast<V*>(o0 + 2 * ldc) = c20;
        *reinterpret_cast<V*>(o0 + 2 * ldc + W1) = c21;
        *reinterpret_cast<V*>(o0 + 3 * ldc) = c30;
        *reinterpret_cast<V*>(o0 + 3 * ldc + W1) = c31;
      }
      for (; r < rows; ++r) {
        V c0 = {}, c1 = {};
        const S* a0 = A + r * rs;
        const S* w = Wp + j0;
        for (int64_t kk = 0; kk < k; ++kk, w += np) {
          const S x0 = a0[kk * cs];
          c0 += x0 * *reinterpret_cast<const V*>(w);
          c1 += x0 * *reinterpret_cast<const V*>(w + W1);
        }
        *reinterpret_cast<V*>(C + r * ldc + j0) = c0;
        *reinterpret_cast<V*>(C + r * ldc + j0 + W1) = c1;
      }
    }
    if (j0 < np) {  // one vector of columns left (np is a multiple of one vector): 8 rows x 1 vector
      int64_t r = 0;
      for (; r + 8 <= rows; r += 8) {
        V c[8] = {};
        const S* a0 = A + r * rs;
        const S* w = Wp + j0;
        for (int64_t kk = 0; kk < k; ++kk, w += np) {
          const V w0 = *reinterpret_cast<const V*>(w);
          const S* ak = a0 + kk * cs;
          c[0] += ak[0] * w0;
          c[1] += ak[rs] * w0;
          c[2] += ak[2 * rs] * w0;
          c[3] += ak[3 * rs] * w0;
          c[4] += ak[4 * rs] * w0;
          c[5] += ak[5 * rs] * w0;
          c[6] += ak[6 * rs] * w0;
          c[7] += ak[7 * rs] * w0;
        }
        for (int q = 0; q < 8; ++q) *reinterpret_cast<V*>(C + (r + q) * ldc + j0) = c[q];
      }
      for (; r < rows; ++r) {
        V c0 = {};
        const S* a0 = A + r * rs;
        const S* w = Wp + j0;
        for (int64_t kk = 0; kk < k; ++kk, w += np) c0 += a0[kk * cs] * *reinterpret_cast<const V*>(w);
        *reinterpret_cast<V*>(C + r * ldc + j0) = c0;
      }
    }
  }

  static int64_t padded(int64_t n, int64_t nb) { return (n + nb - 1) / nb * nb; }

  template <typename S>
  std::vector<S>& scratch();

  template <typename S>
  void run_impl(int64_t s0, int64_t s1, at::Tensor stats_t) {
    const int64_t E = E_, B = B_, L = L_, T = T_, K = K_, NY = ny_;
    S* flat = ptr<S>(FLAT);
    S* grad = ptr<S>(GRAD);
    S* pm = ptr<S>(M);
    S* pv = ptr<S>(V);
    S* lam = ptr<S>(LAM);
    const int64_t ls0 = ts_[LAM].numel() ? ts_[LAM].stride(0) : 0;
    const int64_t ls1 = ts_[LAM].numel() ? ts_[LAM].stride(1) : 0;
    S* dm = ptr<S>(DM);
    S* dv = ptr<S>(DV);
    S* xi = ptr<S>(XI);
    const S* src_z = ptr<S>(SRC_Z);
    const S* src_r = ptr<S>(SRC_R);
    const S* src_mask = ptr<S>(SRC_MASK);
    const S* src_ny = ptr<S>(SRC_NY);
    const S* ostd = ptr<S>(OSTD);
    int64_t* counts = ts_[COUNTS].data_ptr<int64_t>();
    const int64_t* idx_all = idx_.data_ptr<int64_t>();
    S* vals_all = vals_.data_ptr<S>();
    const double* lrs = lrs_.data_ptr<double>();
    double* stats = stats_t.data_ptr<double>();
    const int64_t dz = dims_[0] + 1;
    const int64_t n_chunk = idx_.size(0);

    // scratch (padded widths np(d) = d rounded up to NB; padding columns hold zeros or values times zero):
    // per layer input H[i] (B x (d_i + 1), ones column last), per hidden layer AN = min(a, 0) and the PReLU
    // derivative D (B x np), the pre-activation A, the output OUT (B x np(NY)), err / dpred (B x NY), gradient
    // buffers G, GH (B x np_max), the packed weights WP and the weight gradient CG ((max_d + 1) x np_max)
    constexpr int64_t NB = VEC_BYTES / sizeof(S);  // widths are padded to whole vectors
    const int64_t np_max = padded(max_d_, 2 * NB);
    std::vector<int64_t> h_off(L + 1), an_off(L), d_off(L);
    int64_t tot = 0;
    for (int64_t i = 0; i < L; ++i) {
      h_off[i] = tot;
      tot += B * (dims_[i] + 1);
    }
    for (int64_t i = 0; i + 1 < L; ++i) {
      an_off[i] = tot;
      tot += B * padded(dims_[i + 1], NB);
      d_off[i] = tot;
      tot += B * padded(dims_[i + 1], NB);
    }
    const int64_t a_off = tot;
    tot += B * np_max;
    const int64_t out_off = tot;
    tot += B * np_max;
    const int64_t err_off = tot;
    tot += B * NY;
    const int64_t dp_off = tot;
    tot += B * NY;
    const int64_t g_off = tot;
    tot += B * np_max;
    const int64_t gh_off = tot;
    tot += B * np_max;
    const int64_t wp_off = tot;
    tot += (max_d_ + 1) * np_max;
    const int64_t cg_off = tot;
    tot += (max_d_ + 1) * np_max;
    const int64_t lv_off = tot;
    tot += B * T;
    const int64_t acc_off = tot;
    tot += np_max;
    std::vector<S>& buf = scratch<S>();
    if ((int64_t)buf.size() < tot + NB) buf.assign(tot + NB, S(0));
    S* bs = buf.data();
    // the ones columns of the hidden activations
    for (int64_t i = 1; i < L; ++i) {
      S* h = bs + h_off[i];
      const int64_t w = dims_[i] + 1;
      for (int64_t b = 0; b < B; ++b) h[b * w + dims_[i]] = S(1);
    }
    std::vector<int64_t> rows_d(B);
    std::vector<S> row(T), coef(T), cw(T), gdual(K > 0 ? K : 1), lam_old(K > 0 ? K : 1);
    std::vector<int64_t> cnt(T);
    double worst = -std::numeric_limits<double>::infinity(), total = 0.0;
    bool nan_seen = false;

    for (int64_t s = s0; s < s1; ++s) {
      const int64_t* idx = idx_all + s * E * B;
      S* vals = vals_all + s * E * T;
      double obj_sum = 0.0;
      for (int64_t e = 0; e < E; ++e) {
        const int64_t* ie = idx + e * B;
        const int64_t zoff = z_per_member_ ? e * n_ : 0;
        const int64_t doff = per_member_ ? e * n_ : 0;
        // gather z and f_hat - y (masks and ||y|| are read in place)
        S* h0 = bs + h_off[0];
        for (int64_t b = 0; b < B; ++b) {
          const S* src = src_z + (ie[b] + zoff) * dz;
          S* dst = h0 + b * dz;
          for (int64_t c = 0; c < dz; ++c) dst[c] = src[c];
        }
        S* err = bs + err_off;
        for (int64_t b = 0; b < B; ++b) {
          const int64_t rr = ie[b] + doff;
          rows_d[b] = rr;
          const S* src = src_r + rr * NY;
          S* dst = err + b * NY;
          for (int64_t f = 0; f < NY; ++f) dst[f] = src[f];
        }
        // prefetch the next minibatch's rows (random rows of the sources: cache misses that now overlap with
        // this member's arithmetic)
        {
          const int64_t nxt = s * E + e + 1;
          if (nxt < n_chunk * E) {
            const int64_t* in = idx_all + nxt * B;
            const int64_t ne = nxt % E;
            const int64_t nz = z_per_member_ ? ne * n_ : 0, nd = per_member_ ? ne * n_ : 0;
            for (int64_t b = 0; b < B; ++b) {
              const char* pz = reinterpret_cast<const char*>(src_z + (in[b] + nz) * dz);
              __builtin_prefetch(pz);
              __builtin_prefetch(pz + sizeof(S) * (dz - 1));
              const char* pr = reinterpret_cast<const char*>(src_r + (in[b] + nd) * NY);
              __builtin_prefetch(pr);
              __builtin_prefetch(pr + sizeof(S) * (NY - 1));
              __builtin_prefetch(src_mask + (in[b] + nd) * T);
            }
          }
        }
        // forward
        S* wp = bs + wp_off;
        for (int64_t i = 0; i < L; ++i) {
          const int64_t din = dims_[i] + 1, dout = dims_[i + 1], np = padded(dout, NB);
          const S* W = flat + w_off_[i] + e * din * dout;
          for (int64_t r = 0; r < din; ++r) {
            S* wr = wp + r * np;
            const S* src = W + r * dout;
            for (int64_t c = 0; c < dout; ++c) wr[c] = src[c];
            for (int64_t c = dout; c < np; ++c) wr[c] = S(0);
          }
          const S* hin = bs + h_off[i];
          if (i + 1 < L) {
            S* av = bs + a_off;
            gemm<S>(B, din, hin, din, 1, wp, np, av, np);
            // PReLU: h = a * d with d = 1 where a >= 0 (the plain model's tie rule), else the slope
            const S slope = flat[s_off_ + i * E + e];
            S* an = bs + an_off[i];
            S* dd = bs + d_off[i];
#pragma GCC ivdep
            for (int64_t t = 0; t < B * np; ++t) {
              const S x = av[t];
              an[t] = x > S(0) ? S(0) : x;
              dd[t] = x >= S(0) ? S(1) : slope;
            }
            S* hout = bs + h_off[i + 1];
            const int64_t wo = dout + 1;
            for (int64_t b = 0; b < B; ++b) {
              const S* ar = av + b * np;
              const S* dr = dd + b * np;
              S* hr = hout + b * wo;
#pragma GCC ivdep
              for (int64_t j = 0; j < dout; ++j) hr[j] = ar[j] * dr[j];
            }
          } else {
            gemm<S>(B, din, hin, din, 1, wp, np, bs + out_off, np);
          }
        }
        // err = (f_hat - y) + out * ostd
        const S* os = ostd + e * NY;
        const S* out = bs + out_off;
        const int64_t np_y = padded(NY, NB);
        for (int64_t b = 0; b < B; ++b) {
          S* er = err + b * NY;
          const S* orow = out + b * np_y;
#pragma GCC ivdep
          for (int64_t f = 0; f < NY; ++f) er[f] = er[f] + orow[f] * os[f];
        }
        // spec values: per-sample loss per term, masked sums, denominators
        S* lv = bs + lv_off;
        for (int64_t j = 0; j < T; ++j) {
          const auto& fl = fields_[j];
          const S delta = S(delta_[j]);
          S sum = S(0), count = S(0);
          for (int64_t b = 0; b < B; ++b) {
            const S* eb = err + b * NY;
            S l = S(0);
            switch (loss_[j]) {
              case L2:
              case NORMALIZED: {
                S acc = S(0);
                FOR_FIELDS(j, f, acc += eb[f] * eb[f];)
                l = std::sqrt(acc);
                if (loss_[j] == NORMALIZED) l = l / src_ny[rows_d[b] * T + j];
                break;
              }
              case SQUARED_L2:
                FOR_FIELDS(j, f, l += eb[f] * eb[f];)
                break;
              case L1:
                FOR_FIELDS(j, f, l += std::abs(eb[f]);)
                break;
              default:
                for (int64_t f : fl) {
                  const S ab = std::abs(eb[f]);
                  l += ab <= delta ? S(0.5) * eb[f] * eb[f] : delta * (ab - S(0.5) * delta);
                }
            }
            lv[b * T + j] = l;
            const S m = src_mask[rows_d[b] * T + j];
            sum += l * m;
            count += m;
          }
          const bool c = cond_[j];
          const S den = c ? std::max(count, S(1)) : S(B);
          const bool valid = !c || count > S(0);
          const S negeps = valid ? S(-teps_[j]) : S(0);
          row[j] = negeps + sum / den;
          cw[j] = loss_[j] == SQUARED_L2 ? den / S(2) : den;  // wden
          cnt[j] = 0;
        }
        for (int64_t j = 0; j < T; ++j) vals[e * T + j] = row[j];
        const double o = double(row[0]);
        obj_sum += o;
        // weights of the estimates in the primal gradient
        coef[0] = S(1);
        for (int64_t k = 0; k < K; ++k) {
          const S l = lam[e * ls0 + k * ls1];
          lam_old[k] = l;
          if (method_ == M_AUGMENTED) {
            const S w = l + S(rho_[k]) * row[1 + k];
            coef[1 + k] = w < S(0) ? S(0) : w;
          } else {
            coef[1 + k] = l;
          }
        }
        for (int64_t j = 0; j < T; ++j) cw[j] = coef[j] / cw[j];
        // dL/dpred (times ostd: the gradient at the network's output)
        S* dp = bs + dp_off;
        for (int64_t i = 0; i < B * NY; ++i) dp[i] = S(0);
        for (int64_t j = 0; j < T; ++j) {
          const auto& fl = fields_[j];
          const S delta = S(delta_[j]);
          const S c = cw[j];
          for (int64_t b = 0; b < B; ++b) {
            const S wgt = src_mask[rows_d[b] * T + j] * c;
            const S* eb = err + b * NY;
            S* db = dp + b * NY;
            switch (loss_[j]) {
              case L2:
              case NORMALIZED: {
                S fac;
                if (loss_[j] == NORMALIZED) {  // e / (||e|| ||y||): the per-sample value was ||e|| / ||y||
                  const S ny = src_ny[rows_d[b] * T + j];
                  S acc = S(0);
                  FOR_FIELDS(j, f, acc += eb[f] * eb[f];)
                  fac = wgt / ny / std::max(std::sqrt(acc), S(TINY));
                } else {
                  fac = wgt / std::max(lv[b * T + j], S(TINY));
                }
                FOR_FIELDS(j, f, db[f] += eb[f] * fac;)
                break;
              }
              case SQUARED_L2:
                FOR_FIELDS(j, f, db[f] += eb[f] * wgt;)
                break;
              case L1:
                for (int64_t f : fl) {
                  const S x = eb[f];
                  const S sg = x > S(0) ? S(1) : (x < S(0) ? S(-1) : x);  // torch.sign (NaN stays NaN)
                  db[f] += sg * wgt;
                }
                break;
              default:
                for (int64_t f : fl) {
                  const S x = eb[f];
                  const S cl = x < -delta ? -delta : (x > delta ? delta : x);
                  db[f] += cl * wgt;
                }
            }
          }
        }
        // backward: G (B x np(d_out)) is dL/da of layer i, padding columns zero
        S* g = bs + g_off;
        for (int64_t b = 0; b < B; ++b) {
          S* gr = g + b * np_y;
          const S* dr = dp + b * NY;
          for (int64_t f = 0; f < NY; ++f) gr[f] = dr[f] * os[f];
          for (int64_t f = NY; f < np_y; ++f) gr[f] = S(0);
        }
        S* cg = bs + cg_off;
        for (int64_t i = L - 1; i >= 0; --i) {
          const int64_t din = dims_[i] + 1, dout = dims_[i + 1], np = padded(dout, NB);
          // dW (with the bias row) = H^T G
          const S* hin = bs + h_off[i];
          gemm<S>(din, B, hin, 1, din, g, np, cg, np);
          S* gw = grad + w_off_[i] + e * din * dout;
          for (int64_t r = 0; r < din; ++r) {
            const S* src = cg + r * np;
            S* dst = gw + r * dout;
            for (int64_t c = 0; c < dout; ++c) dst[c] = src[c];
          }
          if (i == 0) break;
          // GH = G W^T (without the bias row), with W^T packed (dout x np(dprev))
          const S* W = flat + w_off_[i] + e * din * dout;
          const int64_t dprev = din - 1, npp = padded(dprev, NB);
          for (int64_t c = 0; c < dout; ++c) {
            S* wr = wp + c * npp;
            for (int64_t a = 0; a < dprev; ++a) wr[a] = W[a * dout + c];
            for (int64_t a = dprev; a < npp; ++a) wr[a] = S(0);
          }
          S* gh = bs + gh_off;
          gemm<S>(B, dout, g, np, 1, wp, npp, gh, npp);
          // slope gradient sum(GH * AN) (per-column partial sums: a vectorised loop), then G <- GH * D
          const S* an = bs + an_off[i - 1];
          const S* dd = bs + d_off[i - 1];
          S* acc = bs + acc_off;
          for (int64_t c = 0; c < npp; ++c) acc[c] = S(0);
          for (int64_t b = 0; b < B; ++b) {
            const S* ghr = gh + b * npp;
            const S* anr = an + b * npp;
#pragma GCC ivdep
            for (int64_t c = 0; c < npp; ++c) acc[c] += ghr[c] * anr[c];
          }
          S gs = S(0);
          for (int64_t c = 0; c < dprev; ++c) gs += acc[c];
          grad[s_off_ + (i - 1) * E + e] = gs;
#pragma GCC ivdep
          for (int64_t t = 0; t < B * npp; ++t) g[t] = gh[t] * dd[t];
        }
        // the dual's gradient (what lambda ascends on) from this step's values, lambda before the update
        for (int64_t k = 0; k < K; ++k) {
          const S gk = row[1 + k];
          S a;
          if (method_ == M_AUGMENTED) {
            a = gk * S(rho_[k]);
          } else if (method_ == M_RESILIENT) {
            const S f = row[0] < S(F_MIN) ? S(F_MIN) : row[0];
            const S dec = S(eps2_[k]) / f;
            a = gk - lam_old[k] * dec;
          } else if (method_ == M_NUPI) {
            a = gk / S(deps_k_[k]);
          } else {
            a = gk;
          }
          if (dopt_ == D_MERGED) {
            grad[x_off_ + e * n_extra_ + k] = a;
          } else {
            gdual[k] = a;
          }
        }
        if (dopt_ != D_MERGED && dopt_ != D_NONE) {
          // a separate dual optimizer steps after the primal step (below): keep the member's ascent direction
          std::memcpy(dual_grad_<S>(e, K), gdual.data(), sizeof(S) * K);
        }
      }
      // primal step on the whole flat tensor (and the merged dual)
      const double lr_p = lrs[s * 2 + 0];
      const double lr_d = lrs[s * 2 + 1];
      if (popt_ == ADAM) {
        const int64_t t = ++counts[0];
        const double bc1 = 1.0 - std::pow(b1_, double(t));
        const double bc2 = 1.0 - std::pow(b2_, double(t));
        const double step_size = (lr_p / bc1) * -1.0;
        const double bc2s = std::pow(bc2, 0.5);
        const S w1 = S(1.0 - b1_), b2 = S(b2_), w2 = S(1.0 - b2_);
        const S epsb = S(peps_ * bc2s), val = S(step_size * bc2s);
#pragma GCC ivdep
        for (int64_t i = 0; i < P_; ++i) {
          const S gi = grad[i];
          const S mi = lerp_<S>(pm[i], gi, w1);
          const S vi = pv[i] * b2 + w2 * gi * gi;
          pm[i] = mi;
          pv[i] = vi;
          flat[i] = flat[i] + val * (mi / (std::sqrt(vi) + epsb));
        }
      } else {
        const S a = S(-lr_p);
#pragma GCC ivdep
        for (int64_t i = 0; i < P_; ++i) flat[i] = flat[i] + a * grad[i];
      }
      // dual step and projection
      if (dopt_ == D_MERGED) {
        const S kd = S(k_dual_);
        for (int64_t e = 0; e < E; ++e) {
          for (int64_t k = 0; k < K; ++k) {
            S& u = flat[x_off_ + e * n_extra_ + k];
            u = u > S(0) ? S(0) : u;
            lam[e * ls0 + k * ls1] = u * kd;
          }
        }
      } else if (dopt_ == D_ADAM) {
        const int64_t t = ++counts[1];
        const double bc1 = 1.0 - std::pow(db1_, double(t));
        const double bc2 = 1.0 - std::pow(db2_, double(t));
        const double step_size = -((lr_d / bc1) * -1.0);  // maximize
        const double bc2s = std::pow(bc2, 0.5);
        const S w1 = S(1.0 - db1_), b2 = S(db2_), w2 = S(1.0 - db2_);
        const S epsb = S(deps_ * bc2s), val = S(step_size * bc2s);
        for (int64_t e = 0; e < E; ++e) {
          const S* gd = dual_grad_<S>(e, K);
          for (int64_t k = 0; k < K; ++k) {
            const int64_t i = e * K + k;
            const S gi = gd[k];
            const S mi = lerp_<S>(dm[i], gi, w1);
            const S vi = dv[i] * b2 + w2 * gi * gi;
            dm[i] = mi;
            dv[i] = vi;
            S& l = lam[e * ls0 + k * ls1];
            l = l + val * (mi / (std::sqrt(vi) + epsb));
            l = l < S(0) ? S(0) : l;
          }
        }
      } else if (dopt_ == D_SGD) {
        const S a = S(lr_d);
        for (int64_t e = 0; e < E; ++e) {
          const S* gd = dual_grad_<S>(e, K);
          for (int64_t k = 0; k < K; ++k) {
            S& l = lam[e * ls0 + k * ls1];
            l = l + a * gd[k];
            l = l < S(0) ? S(0) : l;
          }
        }
      } else if (dopt_ == D_NUPI) {
        const bool first = counts[3] == 0;
        const S lr = S(lr_d), kpn = S(kp_ * (1.0 - nu_)), nu = S(nu_), wn = S(1.0 - nu_);
        for (int64_t e = 0; e < E; ++e) {
          const S* gd = dual_grad_<S>(e, K);
          for (int64_t k = 0; k < K; ++k) {
            const S err = gd[k];
            S& x = xi[e * K + k];
            S upd;
            if (first) {
              upd = err;
              x = err;
            } else {
              upd = (err - x) * kpn + err;
              x = x * nu + wn * err;
            }
            S& l = lam[e * ls0 + k * ls1];
            l = l + lr * upd;
            l = l < S(0) ? S(0) : l;
          }
        }
        counts[3] = 1;
        ++counts[2];
      }
      if (std::isnan(obj_sum)) nan_seen = true;
      if (obj_sum > worst) worst = obj_sum;
      total += obj_sum;
    }
    // the largest magnitude of the weights (flat, lambda) after the block
    double big = 0.0;
    for (int64_t i = 0; i < P_; ++i) {
      const double a = std::abs(double(flat[i]));
      if (!(a <= big)) big = a;  // NaN sticks
      if (std::isnan(big)) break;
    }
    if (!std::isnan(big)) {
      for (int64_t e = 0; e < E; ++e)
        for (int64_t k = 0; k < K; ++k) {
          const double a = std::abs(double(lam[e * ls0 + k * ls1]));
          if (!(a <= big)) big = a;
        }
    }
    const int64_t ns = s1 - s0;
    stats[0] = nan_seen ? std::numeric_limits<double>::quiet_NaN() : worst;
    stats[1] = nan_seen ? std::numeric_limits<double>::quiet_NaN() : (ns ? total / double(ns) : 0.0);
    stats[2] = big;
  }

  template <typename S>
  void evaluate_impl(double* sums, double* counts) {
    constexpr int64_t NB = VEC_BYTES / sizeof(S);
    const int64_t L = L_, T = T_, NY = ny_, R = 256;
    const S* flat = ptr<S>(FLAT);
    const S* src_z = ptr<S>(SRC_Z);
    const S* src_r = ptr<S>(SRC_R);
    const S* src_mask = ptr<S>(SRC_MASK);
    const S* src_ny = ptr<S>(SRC_NY);
    const S* ostd = ptr<S>(OSTD);
    const int64_t dz = dims_[0] + 1, np_max = padded(max_d_, 2 * NB);
    std::vector<S> h(R * (max_d_ + 1)), a(R * np_max), wp((max_d_ + 1) * np_max), err(R * NY);
    for (int64_t i = 0; i < E_ * T; ++i) sums[i] = counts[i] = 0.0;
    for (int64_t e = 0; e < E_; ++e) {
      const int64_t zoff = z_per_member_ ? e * n_ : 0, doff = per_member_ ? e * n_ : 0;
      for (int64_t r0 = 0; r0 < n_; r0 += R) {
        const int64_t nr = std::min(R, n_ - r0);
        // layer by layer: h holds the layer's input rows with their ones column
        for (int64_t b = 0; b < nr; ++b)
          for (int64_t c = 0; c < dz; ++c) h[b * dz + c] = src_z[(r0 + b + zoff) * dz + c];
        for (int64_t i = 0; i < L; ++i) {
          const int64_t din = dims_[i] + 1, dout = dims_[i + 1], np = padded(dout, NB);
          const S* W = flat + w_off_[i] + e * din * dout;
          for (int64_t r = 0; r < din; ++r) {
            for (int64_t c = 0; c < dout; ++c) wp[r * np + c] = W[r * dout + c];
            for (int64_t c = dout; c < np; ++c) wp[r * np + c] = S(0);
          }
          gemm<S>(nr, din, h.data(), din, 1, wp.data(), np, a.data(), np);
          if (i + 1 < L) {
            const S slope = flat[s_off_ + i * E_ + e];
            for (int64_t b = 0; b < nr; ++b) {
              for (int64_t j = 0; j < dout; ++j) {
                const S x = a[b * np + j];
                h[b * (dout + 1) + j] = x * (x >= S(0) ? S(1) : slope);
              }
              h[b * (dout + 1) + dout] = S(1);
            }
          }
        }
        const int64_t np_y = padded(NY, NB);
        const S* os = ostd + e * NY;
        for (int64_t b = 0; b < nr; ++b)
          for (int64_t f = 0; f < NY; ++f)
            err[b * NY + f] = src_r[(r0 + b + doff) * NY + f] + a[b * np_y + f] * os[f];
        for (int64_t j = 0; j < T; ++j) {
          const auto& fl = fields_[j];
          const S delta = S(delta_[j]);
          double sum = 0.0, cnt = 0.0;
          for (int64_t b = 0; b < nr; ++b) {
            const S* eb = err.data() + b * NY;
            const int64_t rr = r0 + b + doff;
            S l = S(0);
            switch (loss_[j]) {
              case L2:
              case NORMALIZED: {
                S acc = S(0);
                FOR_FIELDS(j, f, acc += eb[f] * eb[f];)
                l = std::sqrt(acc);
                if (loss_[j] == NORMALIZED) l = l / src_ny[rr * T + j];
                break;
              }
              case SQUARED_L2:
                FOR_FIELDS(j, f, l += eb[f] * eb[f];)
                break;
              case L1:
                FOR_FIELDS(j, f, l += std::abs(eb[f]);)
                break;
              default:
                for (int64_t f : fl) {
                  const S ab = std::abs(eb[f]);
                  l += ab <= delta ? S(0.5) * eb[f] * eb[f] : delta * (ab - S(0.5) * delta);
                }
            }
            const double m = double(src_mask[rr * T + j]);
            sum += double(l) * m;
            cnt += cond_[j] ? m : 1.0;
          }
          sums[e * T + j] += sum;
          counts[e * T + j] += cnt;
        }
      }
    }
  }

  template <typename S>
  S* dual_grad_(int64_t e, int64_t K) {
    std::vector<S>& d = dgrad<S>();
    if ((int64_t)d.size() < E_ * std::max<int64_t>(K, 1)) d.assign(E_ * std::max<int64_t>(K, 1), S(0));
    return d.data() + e * K;
  }

  template <typename S>
  std::vector<S>& dgrad();
  std::vector<double> dgrad_d_;
  std::vector<float> dgrad_f_;
};

template <>
std::vector<double>& FusedKernel::scratch<double>() { return scratch_d_; }
template <>
std::vector<float>& FusedKernel::scratch<float>() { return scratch_f_; }
template <>
std::vector<double>& FusedKernel::dgrad<double>() { return dgrad_d_; }
template <>
std::vector<float>& FusedKernel::dgrad<float>() { return dgrad_f_; }

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "saml_ros fused training kernel: blocks of primal-dual steps of an EnsembleMLP ensemble";
  pybind11::class_<FusedKernel>(m, "FusedKernel")
      .def(pybind11::init<std::vector<at::Tensor>, std::vector<int64_t>, std::vector<double>>())
      .def("set_chunk", &FusedKernel::set_chunk)
      .def("run", &FusedKernel::run)
      .def("evaluate", &FusedKernel::evaluate)
      .def("snapshot", &FusedKernel::snapshot)
      .def("restore", &FusedKernel::restore);
  m.attr("VERSION") = 1;
}
