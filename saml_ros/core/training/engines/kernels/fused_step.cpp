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
#include <torch/extension.h>

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
  std::vector<bool> cond_;
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

  // C (rows x n) = A (rows x k, row stride lda) * W (k x n); rows blocked by 4 so a row of W feeds four
  template <typename S>
  static void matmul(const S* A, int64_t lda, int64_t rows, int64_t k, const S* W, int64_t n, S* C) {
    int64_t r = 0;
    for (; r + 4 <= rows; r += 4) {
      S* c0 = C + r * n;
      S* c1 = c0 + n;
      S* c2 = c1 + n;
      S* c3 = c2 + n;
      const S* a0 = A + r * lda;
      const S* a1 = a0 + lda;
      const S* a2 = a1 + lda;
      const S* a3 = a2 + lda;
      for (int64_t j = 0; j < n; ++j) c0[j] = c1[j] = c2[j] = c3[j] = S(0);
      for (int64_t kk = 0; kk < k; ++kk) {
        const S* w = W + kk * n;
        const S h0 = a0[kk], h1 = a1[kk], h2 = a2[kk], h3 = a3[kk];
        for (int64_t j = 0; j < n; ++j) {
          const S wj = w[j];
          c0[j] += h0 * wj;
          c1[j] += h1 * wj;
          c2[j] += h2 * wj;
          c3[j] += h3 * wj;
        }
      }
    }
    for (; r < rows; ++r) {
      S* c0 = C + r * n;
      const S* a0 = A + r * lda;
      for (int64_t j = 0; j < n; ++j) c0[j] = S(0);
      for (int64_t kk = 0; kk < k; ++kk) {
        const S* w = W + kk * n;
        const S h0 = a0[kk];
        for (int64_t j = 0; j < n; ++j) c0[j] += h0 * w[j];
      }
    }
  }

  // G (k x n) = A^T (A: rows x k, stride lda) * D (rows x n)
  template <typename S>
  static void matmul_tn(const S* A, int64_t lda, int64_t rows, int64_t k, const S* D, int64_t n, S* G) {
    for (int64_t i = 0; i < k * n; ++i) G[i] = S(0);
    int64_t r = 0;
    for (; r + 4 <= rows; r += 4) {
      const S* a0 = A + r * lda;
      const S* a1 = a0 + lda;
      const S* a2 = a1 + lda;
      const S* a3 = a2 + lda;
      const S* d0 = D + r * n;
      const S* d1 = d0 + n;
      const S* d2 = d1 + n;
      const S* d3 = d2 + n;
      for (int64_t kk = 0; kk < k; ++kk) {
        S* g = G + kk * n;
        const S h0 = a0[kk], h1 = a1[kk], h2 = a2[kk], h3 = a3[kk];
        for (int64_t j = 0; j < n; ++j) g[j] += h0 * d0[j] + h1 * d1[j] + h2 * d2[j] + h3 * d3[j];
      }
    }
    for (; r < rows; ++r) {
      const S* a0 = A + r * lda;
      const S* d0 = D + r * n;
      for (int64_t kk = 0; kk < k; ++kk) {
        S* g = G + kk * n;
        const S h0 = a0[kk];
        for (int64_t j = 0; j < n; ++j) g[j] += h0 * d0[j];
      }
    }
  }

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

    // scratch: per layer input H[i] (B x (d_i + 1), ones column last), AN / D per hidden layer (B x d_{i+1}),
    // out / err / dpred (B x NY), gradient buffers G, GH (B x max_d), WT (max_d x max_d), per-term loss (B)
    std::vector<int64_t> h_off(L + 1), an_off(L), d_off(L);
    int64_t tot = 0;
    for (int64_t i = 0; i < L; ++i) {
      h_off[i] = tot;
      tot += B * (dims_[i] + 1);
    }
    for (int64_t i = 0; i + 1 < L; ++i) {
      an_off[i] = tot;
      tot += B * dims_[i + 1];
      d_off[i] = tot;
      tot += B * dims_[i + 1];
    }
    const int64_t out_off = tot;
    tot += B * NY;
    const int64_t err_off = tot;
    tot += B * NY;
    const int64_t dp_off = tot;
    tot += B * NY;
    const int64_t g_off = tot;
    tot += B * max_d_;
    const int64_t gh_off = tot;
    tot += B * max_d_;
    const int64_t wt_off = tot;
    tot += max_d_ * max_d_;
    const int64_t lv_off = tot;
    tot += B * T;
    const int64_t mk_off = tot;
    tot += B * T;
    const int64_t ny_off = tot;
    tot += B * T;
    std::vector<S>& buf = scratch<S>();
    if ((int64_t)buf.size() < tot) buf.assign(tot, S(0));
    S* bs = buf.data();
    // the ones columns of the hidden activations
    for (int64_t i = 1; i < L; ++i) {
      S* h = bs + h_off[i];
      const int64_t w = dims_[i] + 1;
      for (int64_t b = 0; b < B; ++b) h[b * w + dims_[i]] = S(1);
    }
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
        // gather z, f_hat - y, masks and ||y||
        S* h0 = bs + h_off[0];
        for (int64_t b = 0; b < B; ++b) {
          std::memcpy(h0 + b * dz, src_z + (ie[b] + zoff) * dz, sizeof(S) * dz);
        }
        S* err = bs + err_off;
        S* mk = bs + mk_off;
        S* nyb = bs + ny_off;
        for (int64_t b = 0; b < B; ++b) {
          const int64_t rr = ie[b] + doff;
          std::memcpy(err + b * NY, src_r + rr * NY, sizeof(S) * NY);
          std::memcpy(mk + b * T, src_mask + rr * T, sizeof(S) * T);
          std::memcpy(nyb + b * T, src_ny + rr * T, sizeof(S) * T);
        }
        // forward
        for (int64_t i = 0; i < L; ++i) {
          const int64_t din = dims_[i] + 1, dout = dims_[i + 1];
          const S* W = flat + w_off_[i] + e * din * dout;
          S* hin = bs + h_off[i];
          if (i + 1 < L) {
            // the pre-activation a into the G buffer (free during the forward pass), then PReLU
            matmul<S>(hin, din, B, din, W, dout, bs + g_off);
            const S slope = flat[s_off_ + i * E + e];
            S* an = bs + an_off[i];
            S* dd = bs + d_off[i];
            S* hout = bs + h_off[i + 1];
            const int64_t wo = dout + 1;
            const S* av = bs + g_off;
            for (int64_t b = 0; b < B; ++b) {
              const S* ar = av + b * dout;
              S* anr = an + b * dout;
              S* dr = dd + b * dout;
              S* hr = hout + b * wo;
              for (int64_t j = 0; j < dout; ++j) {
                const S x = ar[j];
                const S d = std::signbit(x) ? slope : S(1);
                anr[j] = x > S(0) ? S(0) : x;
                dr[j] = d;
                hr[j] = x * d;
              }
            }
          } else {
            matmul<S>(hin, din, B, din, W, dout, bs + out_off);
          }
        }
        // err = (f_hat - y) + out * ostd
        const S* os = ostd + e * NY;
        const S* out = bs + out_off;
        for (int64_t b = 0; b < B; ++b) {
          for (int64_t f = 0; f < NY; ++f) err[b * NY + f] = err[b * NY + f] + out[b * NY + f] * os[f];
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
                for (int64_t f : fl) acc += eb[f] * eb[f];
                l = std::sqrt(acc);
                if (loss_[j] == NORMALIZED) l = l / nyb[b * T + j];
                break;
              }
              case SQUARED_L2:
                for (int64_t f : fl) l += eb[f] * eb[f];
                break;
              case L1:
                for (int64_t f : fl) l += std::abs(eb[f]);
                break;
              default:
                for (int64_t f : fl) {
                  const S ab = std::abs(eb[f]);
                  l += ab <= delta ? S(0.5) * eb[f] * eb[f] : delta * (ab - S(0.5) * delta);
                }
            }
            lv[b * T + j] = l;
            const S m = mk[b * T + j];
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
            const S wgt = mk[b * T + j] * c;
            const S* eb = err + b * NY;
            S* db = dp + b * NY;
            switch (loss_[j]) {
              case L2:
              case NORMALIZED: {
                S fac;
                if (loss_[j] == NORMALIZED) {  // e / (||e|| ||y||): the per-sample value was ||e|| / ||y||
                  const S ny = nyb[b * T + j];
                  S acc = S(0);
                  for (int64_t f : fl) acc += eb[f] * eb[f];
                  fac = wgt / ny / std::max(std::sqrt(acc), S(TINY));
                } else {
                  fac = wgt / std::max(lv[b * T + j], S(TINY));
                }
                for (int64_t f : fl) db[f] += eb[f] * fac;
                break;
              }
              case SQUARED_L2:
                for (int64_t f : fl) db[f] += eb[f] * wgt;
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
        // backward
        S* g = bs + g_off;
        for (int64_t b = 0; b < B; ++b) {
          for (int64_t f = 0; f < NY; ++f) g[b * NY + f] = dp[b * NY + f] * os[f];
        }
        for (int64_t i = L - 1; i >= 0; --i) {
          const int64_t din = dims_[i] + 1, dout = dims_[i + 1];
          S* gw = grad + w_off_[i] + e * din * dout;
          const S* hin = bs + h_off[i];
          matmul_tn<S>(hin, din, B, din, g, dout, gw);
          if (i == 0) break;
          // gh = g W^T (without the bias row), through WT (dout x (din - 1))
          const S* W = flat + w_off_[i] + e * din * dout;
          S* wt = bs + wt_off;
          const int64_t dprev = din - 1;
          for (int64_t a = 0; a < dprev; ++a)
            for (int64_t c = 0; c < dout; ++c) wt[c * dprev + a] = W[a * dout + c];
          S* gh = bs + gh_off;
          matmul<S>(g, dout, B, dout, wt, dprev, gh);
          // slope gradient and g <- gh * d
          const S* an = bs + an_off[i - 1];
          const S* dd = bs + d_off[i - 1];
          S gs = S(0);
          for (int64_t t = 0; t < B * dprev; ++t) gs += gh[t] * an[t];
          grad[s_off_ + (i - 1) * E + e] = gs;
          for (int64_t t = 0; t < B * dprev; ++t) g[t] = gh[t] * dd[t];
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
      .def("snapshot", &FusedKernel::snapshot)
      .def("restore", &FusedKernel::restore);
  m.attr("VERSION") = 1;
}
