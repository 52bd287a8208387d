// Ceres Solver twin of planetref's line-scan bundle adjustment (benchmark only).
//
// Reads a problem written by benchmarks/ceres_problem.py (format "PRCERES1", documented
// there), builds one residual block per observation and solves it with the linear solver
// and thread count given on the command line. The model is planetref's
// (src/planetref/camera/linescan/kernel.py, _numba_kernel.py), written again here:
//
//   line -> time: piecewise-linear line-rate table;
//   time -> exterior orientation: Lagrange interpolation of the k nodes of the window
//     (t in [t_i, t_i+1) uses nodes i-k/2+1 .. i+k/2, clamped to the ends), here in the
//     product form (planetref tabulates the same polynomials in powers of tau);
//   rotation: [U, V, W] = (R0 R_phi(Y) R_omega(X) R_kappa(Z))^T (P - S);
//   focal plane: x = x0 - f U/W, y = y0 - f V/W (mm); detector: offset and sample of the
//     CCD line array (placement x_mm, y_mm, angle, pitch).
//
// The projected image line solves offset(line) = 0 (chord steps from the previous
// solution with the previous slope, then one full evaluation and a first-order Newton
// step, exactly as planetref's kernel); the residual is (projected - observed) line and
// sample divided by the observation's sigma: planetref minimises the same weighted sum
// (its residual is observed - projected; the sign does not change the cost). Derivatives
// are analytic, by the implicit-function theorem:
//   dline/dq = -(d offset/dq)/(d offset/dline), dsample/dq = d sample/dq + srate dline/dq.
//
// The set of nodes an observation depends on changes when its projected line crosses a
// node time (the Lagrange window moves on). Each residual block therefore takes every
// node of every window that its line reaches between the initial projection and the
// observed line (plus a margin); the columns of nodes outside the current window are
// zero. A trial step that would move a line beyond that range is reported as invalid
// (Ceres rejects the step and shrinks its trust region).
//
// Output: the adjusted nodes (raw float64, n_nodes x 6) in the file named by --out and
// one JSON object on stdout (Ceres's summary, times, peak memory).

#include <ceres/ceres.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iostream>
#include <limits>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

namespace {

constexpr double kChordTol = 1e-6;   // planetref's CHORD_TOL (pixels)
constexpr double kStepValid = 1e-3;  // planetref's STEP_VALID (pixels)
constexpr int kChordIterations = 40;
constexpr int kMaxK = 16;

struct Model {
  int64_t n_nodes = 0, k = 0, n_rows = 0, n_ccd = 0, n_points = 0, n_obs = 0;
  int64_t pos_free = 0, att_free = 1;
  double lo = 0.0, hi = 0.0;
  std::vector<double> rs, rt0, rp;  // line-rate rows: start line, start time, period
  std::vector<double> times;        // node times (s)
  double r0[9];                     // row-major R0
  std::vector<double> nodes;        // n_nodes x 6: X, Y, Z, phi, omega, kappa
  double io[3];                     // x0, y0, f (mm)
  std::vector<double> ccd;          // n_ccd x 6: x_mm, y_mm, angle, pitch, sin, cos
  std::vector<double> xyz;          // n_points x 3
  std::vector<double> obs_line, obs_sample, obs_sigma;  // obs_sigma: (line, sample) pairs
  std::vector<int32_t> obs_ccd, obs_point;
  std::vector<int32_t> point_free;  // 1: unknown (tie) point, a parameter block

  int RowOf(double line) const {
    int j = static_cast<int>(n_rows) - 1;
    while (j > 0 && rs[j] > line) --j;
    return j;
  }
  // Window start of a time (planetref's LagrangeWindows.window).
  int WindowOf(double t) const {
    int i = static_cast<int>(n_nodes) - 1;
    while (i >= 0 && times[i] > t) --i;
    int s = i - static_cast<int>(k) / 2 + 1;
    return std::clamp(s, 0, static_cast<int>(n_nodes - k));
  }
  // Time and line period of a line.
  void Time(double line, double* t, double* period) const {
    const int j = RowOf(line);
    *t = rt0[j] + (line - rs[j]) * rp[j];
    *period = rp[j];
  }
  // Lagrange weights of window s at time t (and their time derivatives when dw).
  void Weights(int s, double t, double* w, double* dw) const {
    const double* tn = &times[s];
    for (int j = 0; j < k; ++j) {
      double num = 1.0, den = 1.0;
      for (int m = 0; m < k; ++m) {
        if (m == j) continue;
        num *= t - tn[m];
        den *= tn[j] - tn[m];
      }
      w[j] = num / den;
      if (dw) {
        double d = 0.0;
        for (int l = 0; l < k; ++l) {
          if (l == j) continue;
          double p = 1.0;
          for (int m = 0; m < k; ++m) {
            if (m != j && m != l) p *= t - tn[m];
          }
          d += p;
        }
        dw[j] = d / den;
      }
    }
  }
};

template <typename T>
void ReadInto(std::ifstream& f, T* dst, size_t n) {
  f.read(reinterpret_cast<char*>(dst), static_cast<std::streamsize>(n * sizeof(T)));
  if (!f) throw std::runtime_error("problem file is truncated");
}

Model ReadModel(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  if (!f) throw std::runtime_error("cannot open " + path);
  char magic[8];
  ReadInto(f, magic, 8);
  if (std::memcmp(magic, "PRCERES1", 8) != 0) throw std::runtime_error("not a PRCERES1 file");
  Model m;
  int64_t hdr[8];
  ReadInto(f, hdr, 8);
  m.n_nodes = hdr[0];
  m.k = hdr[1];
  m.n_rows = hdr[2];
  m.n_ccd = hdr[3];
  m.n_points = hdr[4];
  m.n_obs = hdr[5];
  m.pos_free = hdr[6];
  m.att_free = hdr[7];
  if (m.k < 2 || m.k > kMaxK || m.k > m.n_nodes) throw std::runtime_error("bad Lagrange order");
  double range[2];
  ReadInto(f, range, 2);
  m.lo = range[0];
  m.hi = range[1];
  std::vector<double> rows(3 * m.n_rows);
  ReadInto(f, rows.data(), rows.size());
  for (int64_t i = 0; i < m.n_rows; ++i) {
    m.rs.push_back(rows[3 * i]);
    m.rt0.push_back(rows[3 * i + 1]);
    m.rp.push_back(rows[3 * i + 2]);
  }
  m.times.resize(m.n_nodes);
  ReadInto(f, m.times.data(), m.times.size());
  ReadInto(f, m.r0, 9);
  m.nodes.resize(6 * m.n_nodes);
  ReadInto(f, m.nodes.data(), m.nodes.size());
  ReadInto(f, m.io, 3);
  std::vector<double> c(4 * m.n_ccd);
  ReadInto(f, c.data(), c.size());
  for (int64_t i = 0; i < m.n_ccd; ++i) {
    const double* ci = &c[4 * i];
    for (int j = 0; j < 4; ++j) m.ccd.push_back(ci[j]);
    m.ccd.push_back(std::sin(ci[2]));
    m.ccd.push_back(std::cos(ci[2]));
  }
  m.xyz.resize(3 * m.n_points);
  ReadInto(f, m.xyz.data(), m.xyz.size());
  m.obs_line.resize(m.n_obs);
  m.obs_sample.resize(m.n_obs);
  m.obs_sigma.resize(2 * m.n_obs);
  m.obs_ccd.resize(m.n_obs);
  m.obs_point.resize(m.n_obs);
  ReadInto(f, m.obs_line.data(), m.n_obs);
  ReadInto(f, m.obs_sample.data(), m.n_obs);
  ReadInto(f, m.obs_sigma.data(), 2 * m.n_obs);
  ReadInto(f, m.obs_ccd.data(), m.n_obs);
  ReadInto(f, m.obs_point.data(), m.n_obs);
  m.point_free.resize(m.n_points);
  ReadInto(f, m.point_free.data(), m.n_points);
  return m;
}

// The collinearity at one time: offset, sample, depth and the intermediate terms the
// partials need (Partials), as planetref's kernel.state / _numba_kernel.collinear.
struct Collinear {
  double off = 0.0, samp = 0.0, w = 0.0;
  double u = 0.0, v = 0.0, a0 = 0.0, a2 = 0.0, b1 = 0.0;
  double cp = 1.0, sp = 0.0, co = 1.0, so = 0.0, ck = 1.0, sk = 0.0;
  double phi = 0.0, omega = 0.0, kappa = 0.0;
  double doff[6], dsmp[6];  // d(offset, sample)/d(S; phi, omega, kappa), by Partials
};

// Angle changes below which cos/sin are updated from a nearby angle's (rad): planetref's
// _NEAR_RAD (chord steps move the attitude by ~1e-9 rad; the 5th-order series of the
// angle-addition formulas are exact to double precision there).
constexpr double kNearRad = 1e-4;

inline void CosSin(double a, double a0, double c0, double s0, bool near, double* c,
                   double* s) {
  const double d = a - a0;
  if (near && std::abs(d) < kNearRad) {
    const double d2 = d * d;
    const double cd = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0));
    const double sd = d * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0)));
    *c = c0 * cd - s0 * sd;
    *s = s0 * cd + c0 * sd;
  } else {
    *c = std::cos(a);
    *s = std::sin(a);
  }
}

// ``prev``: an earlier evaluation of the same point (its cosines seed this one's), or
// nullptr.
void Collinearity(const Model& m, const double* eo, const double* p, const double* ccd,
                  const Collinear* prev, Collinear* out) {
  const double* r0 = m.r0;
  const double e0 = p[0] - eo[0], e1 = p[1] - eo[1], e2 = p[2] - eo[2];
  const double d0 = e0 * r0[0] + e1 * r0[3] + e2 * r0[6];
  const double d1 = e0 * r0[1] + e1 * r0[4] + e2 * r0[7];
  const double d2 = e0 * r0[2] + e1 * r0[5] + e2 * r0[8];
  const bool near = prev != nullptr;
  const Collinear& q = near ? *prev : *out;
  double cp, sp, co, so, ck, sk;
  CosSin(eo[3], q.phi, q.cp, q.sp, near, &cp, &sp);
  CosSin(eo[4], q.omega, q.co, q.so, near, &co, &so);
  CosSin(eo[5], q.kappa, q.ck, q.sk, near, &ck, &sk);
  const double a0 = cp * d0 + sp * d2;
  const double a2 = -sp * d0 + cp * d2;
  const double b1 = co * d1 + so * a2;
  const double b2 = -so * d1 + co * a2;
  const double u = ck * a0 + sk * b1;
  const double v = -sk * a0 + ck * b1;
  const double inv_w = 1.0 / b2;
  const double xn = u * inv_w, yn = v * inv_w;
  const double pitch = ccd[3], sa = ccd[4], ca = ccd[5];
  const double dx = m.io[0] - m.io[2] * xn - ccd[0];
  const double dy = m.io[1] - m.io[2] * yn - ccd[1];
  out->off = (dx * ca - dy * sa) / pitch;
  out->samp = (dx * sa + dy * ca) / pitch;
  out->w = b2;
  out->u = u;
  out->v = v;
  out->a0 = a0;
  out->a2 = a2;
  out->b1 = b1;
  out->cp = cp;
  out->sp = sp;
  out->co = co;
  out->so = so;
  out->ck = ck;
  out->sk = sk;
  out->phi = eo[3];
  out->omega = eo[4];
  out->kappa = eo[5];
}

// The partials of offset and sample w.r.t. the interpolated EO at an evaluation.
void Partials(const Model& m, const double* ccd, Collinear* ev) {
  const double* r0 = m.r0;
  const double cp = ev->cp, sp = ev->sp, co = ev->co, so = ev->so, ck = ev->ck, sk = ev->sk;
  const double a0 = ev->a0, a2 = ev->a2, b1 = ev->b1, b2 = ev->w, u = ev->u, v = ev->v;
  double jac[6][3];
  const double bp1 = so * (-a0);
  jac[3][0] = ck * a2 + sk * bp1;
  jac[3][1] = -sk * a2 + ck * bp1;
  jac[3][2] = co * (-a0);
  jac[4][0] = sk * b2;
  jac[4][1] = ck * b2;
  jac[4][2] = -b1;
  jac[5][0] = v;
  jac[5][1] = -u;
  jac[5][2] = 0.0;
  for (int r = 0; r < 3; ++r) {
    const double g0 = r0[3 * r], g1 = r0[3 * r + 1], g2 = r0[3 * r + 2];
    const double ga0 = cp * g0 + sp * g2;
    const double ga2 = -sp * g0 + cp * g2;
    const double gb1 = co * g1 + so * ga2;
    jac[r][0] = ck * ga0 + sk * gb1;
    jac[r][1] = -sk * ga0 + ck * gb1;
    jac[r][2] = -so * g1 + co * ga2;
  }
  const double inv_w = 1.0 / b2;
  const double xn = u * inv_w, yn = v * inv_w;
  const double pitch = ccd[3], sa = ccd[4], ca = ccd[5];
  const double fw = -m.io[2] * inv_w / pitch;
  const double c_ca = fw * ca, c_sa = fw * sa;
  for (int q = 0; q < 6; ++q) {
    const double dxq = jac[q][0] - xn * jac[q][2];
    const double dyq = jac[q][1] - yn * jac[q][2];
    double doff = dxq * c_ca - dyq * c_sa;
    double dsmp = dxq * c_sa + dyq * c_ca;
    if (q < 3) {  // d/dS = -d/dP
      doff = -doff;
      dsmp = -dsmp;
    }
    ev->doff[q] = doff;
    ev->dsmp[q] = dsmp;
  }
}

// One observation: residual (projected - observed) / sigma of (line, sample).
// Parameter blocks: the attitudes (3) of nodes first..last when attitudes are free, then
// their positions (3) when positions are free, then the ground point (3) when it is an
// unknown (tie) point.
class LineScanCost final : public ceres::CostFunction {
 public:
  LineScanCost(const Model* m, int64_t obs, int first, int last, double line_guess,
               double rate_guess, bool point_block)
      : m_(m),
        obs_(obs),
        first_(first),
        last_(last),
        point_block_(point_block),
        line_(line_guess),
        rate_(rate_guess) {
    set_num_residuals(2);
    const int n = last - first + 1;
    auto* sizes = mutable_parameter_block_sizes();
    if (m->att_free)
      for (int i = 0; i < n; ++i) sizes->push_back(3);
    if (m->pos_free)
      for (int i = 0; i < n; ++i) sizes->push_back(3);
    if (point_block) sizes->push_back(3);
  }

  bool Evaluate(double const* const* params, double* residuals,
                double** jacobians) const override {
    const Model& m = *m_;
    const int k = static_cast<int>(m.k);
    const int n = last_ - first_ + 1;
    const int point_index = (m.att_free ? n : 0) + (m.pos_free ? n : 0);
    const double* p = point_block_ ? params[point_index] : &m.xyz[3 * m.obs_point[obs_]];
    const double* ccd = &m.ccd[6 * m.obs_ccd[obs_]];
    // Node pointers of window s (nullptr when outside this block's node range).
    auto node_value = [&](int node, int c) -> double {
      const int i = node - first_;
      if (c >= 3) return m.att_free ? params[i][c - 3] : m.nodes[6 * node + c];
      if (m.pos_free) return params[(m.att_free ? n : 0) + i][c];
      return m.nodes[6 * node + c];
    };
    double w[kMaxK], dw[kMaxK], eo[6], deo[6];
    int s = 0;
    double period = 0.0;
    auto interpolate = [&](double line, bool derivative) -> bool {
      double t;
      m.Time(line, &t, &period);
      s = m.WindowOf(t);
      if (s < first_ || s + k - 1 > last_) return false;  // beyond this block's nodes
      m.Weights(s, t, w, derivative ? dw : nullptr);
      for (int c = 0; c < 6; ++c) {
        double v = 0.0, dv = 0.0;
        for (int j = 0; j < k; ++j) {
          const double x = node_value(s + j, c);
          v += w[j] * x;
          if (derivative) dv += dw[j] * x;
        }
        eo[c] = v;
        deo[c] = dv;
      }
      return true;
    };
    Collinear ev;
    double line = std::isfinite(line_) ? line_ : 0.5 * (m.lo + m.hi);
    line = std::clamp(line, m.lo, m.hi);
    if (!interpolate(line, false)) return false;
    Collinearity(m, eo, p, ccd, nullptr, &ev);
    double rate = rate_;
    if (!(std::isfinite(rate) && rate != 0.0)) {
      if (!interpolate(line + 1.0, false)) return false;
      Collinear ev1;
      Collinearity(m, eo, p, ccd, &ev, &ev1);
      rate = ev1.off - ev.off;
    }
    double step = -ev.off / rate;
    for (int it = 0; it < kChordIterations; ++it) {
      if (!(std::isfinite(step) && std::abs(step) > kChordTol)) break;
      line = std::clamp(line + step, m.lo, m.hi);
      if (!interpolate(line, false)) return false;
      Collinear next;
      Collinearity(m, eo, p, ccd, &ev, &next);
      ev = next;
      step = -ev.off / rate;
    }
    // The last evaluation is the final one (as planetref's kernel): its terms give the
    // partials; the window's weights and the EO's time derivative at that line, then
    // the analytic slopes and a first-order Newton step.
    if (!interpolate(line, true)) return false;
    Partials(m, ccd, &ev);
    double rate_f = 0.0, srate = 0.0;
    for (int q = 0; q < 6; ++q) {
      rate_f += ev.doff[q] * deo[q];
      srate += ev.dsmp[q] * deo[q];
    }
    rate_f *= period;
    srate *= period;
    step = -ev.off / rate_f;
    const double line_out = line + step;
    const double samp_out = ev.samp + srate * step;
    const bool valid = std::isfinite(line_out) && std::isfinite(samp_out) && ev.w < 0 &&
                       std::abs(step) < kStepValid && line_out >= m.lo && line_out <= m.hi;
    if (!valid) return false;
    // The next evaluation starts from here (each residual block is evaluated by one
    // thread at a time, so this state needs no lock; like planetref's guesses it only
    // seeds the search, the result does not depend on it beyond ~1e-12 px).
    line_ = line_out;
    rate_ = rate_f;
    const double inv_sl = 1.0 / m.obs_sigma[2 * obs_];
    const double inv_ss = 1.0 / m.obs_sigma[2 * obs_ + 1];
    residuals[0] = (line_out - m.obs_line[obs_]) * inv_sl;
    residuals[1] = (samp_out - m.obs_sample[obs_]) * inv_ss;
    if (jacobians == nullptr) return true;
    const double nir = -1.0 / rate_f;
    double imp0[6], imp1[6];
    for (int q = 0; q < 6; ++q) {
      const double dline = ev.doff[q] * nir;
      imp0[q] = dline * inv_sl;
      imp1[q] = (dline * srate + ev.dsmp[q]) * inv_ss;
    }
    int b = 0;
    for (int pass = 0; pass < 2; ++pass) {
      const bool att = pass == 0;
      if (att ? !m.att_free : !m.pos_free) continue;
      const int c0 = att ? 3 : 0;
      for (int i = 0; i < n; ++i, ++b) {
        double* jb = jacobians[b];
        if (jb == nullptr) continue;  // a constant block
        const int j = first_ + i - s;
        const double wj = (j >= 0 && j < k) ? w[j] : 0.0;
        for (int c = 0; c < 3; ++c) {
          jb[c] = imp0[c0 + c] * wj;
          jb[3 + c] = imp1[c0 + c] * wj;
        }
      }
    }
    if (point_block_ && jacobians[point_index] != nullptr) {
      double* jb = jacobians[point_index];
      for (int c = 0; c < 3; ++c) {  // d/dP = -d/dS (the partials before the weights)
        jb[c] = -imp0[c];
        jb[3 + c] = -imp1[c];
      }
    }
    return true;
  }

  double line() const { return line_; }
  double rate() const { return rate_; }

 private:
  const Model* m_;
  int64_t obs_;
  int first_, last_;
  bool point_block_;
  mutable double line_, rate_;
};

// The projected line of an observation at the initial nodes (every window allowed),
// as planetref's first evaluation: chord steps from the observed line. ``blocks``: the
// initial values of every node's blocks, in LineScanCost's order.
double InitialLine(const Model& m, int64_t i, const double* const* blocks, double* rate_out) {
  LineScanCost probe(&m, i, 0, static_cast<int>(m.n_nodes) - 1, m.obs_line[i], NAN, false);
  double r[2];
  if (!probe.Evaluate(blocks, r, nullptr)) return NAN;
  *rate_out = probe.rate();
  return probe.line();
}

double Seconds() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

double CpuSeconds() {
  rusage u;
  getrusage(RUSAGE_SELF, &u);
  return u.ru_utime.tv_sec + u.ru_stime.tv_sec + 1e-6 * (u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

// A /proc/self/status field in MB (VmHWM: peak resident size of this program; unlike
// getrusage's ru_maxrss it does not carry the parent's peak over the exec).
double StatusMb(const char* field) {
  std::ifstream f("/proc/self/status");
  std::string line;
  const std::string key = std::string(field) + ":";
  while (std::getline(f, line)) {
    if (line.rfind(key, 0) == 0) return std::stod(line.substr(key.size())) / 1024.0;
  }
  return NAN;
}

double CurrentRssMb() {
  std::ifstream f("/proc/self/statm");
  long pages = 0, rss = 0;
  f >> pages >> rss;
  return rss * static_cast<double>(sysconf(_SC_PAGESIZE)) / (1024.0 * 1024.0);
}

std::string JsonString(const std::string& s) {
  std::ostringstream o;
  o << '"';
  for (char c : s) {
    if (c == '"' || c == '\\') o << '\\' << c;
    else if (c == '\n') o << "\\n";
    else if (static_cast<unsigned char>(c) < 0x20) o << ' ';
    else o << c;
  }
  o << '"';
  return o.str();
}

struct Args {
  std::string problem, out, solver = "SPARSE_SCHUR", preconditioner = "SCHUR_JACOBI";
  int threads = 1, max_iterations = 50;
  double ftol = 1e-12, ptol = 1e-8, gtol = 0.0, initial_radius = 1e8, margin = 20.0;
  bool covariance = false;
};

Args Parse(int argc, char** argv) {
  Args a;
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto val = [&]() -> std::string {
      if (i + 1 >= argc) throw std::runtime_error("missing value of " + k);
      return argv[++i];
    };
    if (k == "--problem") a.problem = val();
    else if (k == "--out") a.out = val();
    else if (k == "--solver") a.solver = val();
    else if (k == "--preconditioner") a.preconditioner = val();
    else if (k == "--threads") a.threads = std::stoi(val());
    else if (k == "--max-iterations") a.max_iterations = std::stoi(val());
    else if (k == "--ftol") a.ftol = std::stod(val());
    else if (k == "--ptol") a.ptol = std::stod(val());
    else if (k == "--gtol") a.gtol = std::stod(val());
    else if (k == "--initial-radius") a.initial_radius = std::stod(val());
    else if (k == "--margin") a.margin = std::stod(val());
    else if (k == "--covariance") a.covariance = true;
    else throw std::runtime_error("unknown option " + k);
  }
  if (a.problem.empty()) throw std::runtime_error("--problem is required");
  return a;
}

int Run(const Args& a) {
  const double t_start = Seconds(), c_start = CpuSeconds();
  const double rss_start = CurrentRssMb();
  Model m = ReadModel(a.problem);
  const double t_read = Seconds();

  // Parameter blocks: per node an attitude block and a position block (either may be
  // absent when held fixed: the model then reads the node's values as constants).
  std::vector<double> att(3 * m.n_nodes), pos(3 * m.n_nodes);
  for (int64_t n = 0; n < m.n_nodes; ++n)
    for (int c = 0; c < 3; ++c) {
      pos[3 * n + c] = m.nodes[6 * n + c];
      att[3 * n + c] = m.nodes[6 * n + 3 + c];
    }

  std::vector<double> xyz(m.xyz);  // the points' parameter blocks (free points only)

  ceres::Problem::Options popt;
  popt.cost_function_ownership = ceres::TAKE_OWNERSHIP;
  ceres::Problem problem(popt);
  const int k = static_cast<int>(m.k);
  int64_t n_bad = 0, n_wide = 0;
  std::vector<double*> blocks;
  std::vector<const double*> all_blocks;
  if (m.att_free)
    for (int64_t n = 0; n < m.n_nodes; ++n) all_blocks.push_back(&att[3 * n]);
  if (m.pos_free)
    for (int64_t n = 0; n < m.n_nodes; ++n) all_blocks.push_back(&pos[3 * n]);
  for (int64_t i = 0; i < m.n_obs; ++i) {
    double rate0 = NAN;
    const double l0 = InitialLine(m, i, all_blocks.data(), &rate0);
    if (!std::isfinite(l0)) {
      ++n_bad;
      continue;
    }
    const double lmin = std::min(l0, m.obs_line[i]) - a.margin;
    const double lmax = std::max(l0, m.obs_line[i]) + a.margin;
    double t, period;
    m.Time(std::clamp(lmin, m.lo, m.hi), &t, &period);
    const int first = m.WindowOf(t);
    m.Time(std::clamp(lmax, m.lo, m.hi), &t, &period);
    const int last = m.WindowOf(t) + k - 1;
    if (last - first + 1 > k) ++n_wide;
    const int32_t pt = m.obs_point[i];
    const bool free_point = m.point_free[pt] != 0;
    auto* cost = new LineScanCost(&m, i, first, last, l0, rate0, free_point);
    blocks.clear();
    if (m.att_free)
      for (int n = first; n <= last; ++n) blocks.push_back(&att[3 * n]);
    if (m.pos_free)
      for (int n = first; n <= last; ++n) blocks.push_back(&pos[3 * n]);
    if (free_point) blocks.push_back(&xyz[3 * pt]);
    problem.AddResidualBlock(cost, nullptr, blocks);
  }
  int64_t n_free_points = 0;
  for (int32_t f : m.point_free) n_free_points += f != 0;
  if (n_bad) {
    std::cerr << n_bad << " observation(s) cannot be projected with the initial cameras\n";
    return 3;
  }
  const double t_built = Seconds(), c_built = CpuSeconds();
  const double rss_built = CurrentRssMb();

  ceres::Solver::Options o;
  std::string err;
  if (!ceres::StringToLinearSolverType(a.solver, &o.linear_solver_type))
    throw std::runtime_error("unknown linear solver " + a.solver);
  if (!ceres::StringToPreconditionerType(a.preconditioner, &o.preconditioner_type))
    throw std::runtime_error("unknown preconditioner " + a.preconditioner);
  o.minimizer_type = ceres::TRUST_REGION;
  o.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
  o.num_threads = a.threads;
  o.max_num_iterations = a.max_iterations;
  o.function_tolerance = a.ftol;
  o.parameter_tolerance = a.ptol;
  o.gradient_tolerance = a.gtol;
  o.initial_trust_region_radius = a.initial_radius;
  o.minimizer_progress_to_stdout = false;
  o.logging_type = ceres::SILENT;
  if (n_free_points > 0 && (o.linear_solver_type == ceres::DENSE_SCHUR ||
                            o.linear_solver_type == ceres::SPARSE_SCHUR ||
                            o.linear_solver_type == ceres::ITERATIVE_SCHUR)) {
    // The bundle adjustment's ordering: the points are eliminated first (planetref's
    // Schur complement does the same).
    auto ordering = std::make_shared<ceres::ParameterBlockOrdering>();
    for (int64_t pt = 0; pt < m.n_points; ++pt)
      if (m.point_free[pt]) ordering->AddElementToGroup(&xyz[3 * pt], 0);
    for (int64_t n = 0; n < m.n_nodes; ++n) {
      if (m.att_free) ordering->AddElementToGroup(&att[3 * n], 1);
      if (m.pos_free) ordering->AddElementToGroup(&pos[3 * n], 1);
    }
    o.linear_solver_ordering = ordering;
  }
  if (!o.IsValid(&err)) throw std::runtime_error(err);
  ceres::Solver::Summary summary;
  ceres::Solve(o, &problem, &summary);
  const double t_solved = Seconds(), c_solved = CpuSeconds();

  // Optional: the a-priori covariance of the attitude blocks (unit weight), the
  // counterpart of planetref's statistics.
  std::vector<double> sig(3 * m.n_nodes, NAN);
  double t_cov = 0.0, c_cov = 0.0;
  bool cov_ok = false;
  if (a.covariance && m.att_free) {
    ceres::Covariance::Options copt;
    copt.num_threads = a.threads;
    copt.algorithm_type = ceres::SPARSE_QR;
    ceres::Covariance cov(copt);
    std::vector<std::pair<const double*, const double*>> pairs;
    for (int64_t n = 0; n < m.n_nodes; ++n) pairs.emplace_back(&att[3 * n], &att[3 * n]);
    cov_ok = cov.Compute(pairs, &problem);
    if (cov_ok) {
      for (int64_t n = 0; n < m.n_nodes; ++n) {
        double c[9];
        cov.GetCovarianceBlock(&att[3 * n], &att[3 * n], c);
        for (int j = 0; j < 3; ++j) sig[3 * n + j] = std::sqrt(c[4 * j]);
      }
    }
    t_cov = Seconds() - t_solved;
    c_cov = CpuSeconds() - c_solved;
  }

  std::vector<double> out(m.nodes);
  for (int64_t n = 0; n < m.n_nodes; ++n)
    for (int c = 0; c < 3; ++c) {
      out[6 * n + c] = pos[3 * n + c];
      out[6 * n + 3 + c] = att[3 * n + c];
    }
  if (!a.out.empty()) {
    std::ofstream f(a.out, std::ios::binary);
    f.write(reinterpret_cast<const char*>(out.data()), out.size() * sizeof(double));
    f.write(reinterpret_cast<const char*>(sig.data()), sig.size() * sizeof(double));
    if (!f) throw std::runtime_error("cannot write " + a.out);
  }

  std::ostringstream j;
  j.precision(17);
  j << "{";
  j << "\"linear_solver\": " << JsonString(a.solver);
  j << ", \"linear_solver_type_used\": "
    << JsonString(ceres::LinearSolverTypeToString(summary.linear_solver_type_used));
  j << ", \"preconditioner_type_used\": "
    << JsonString(ceres::PreconditionerTypeToString(summary.preconditioner_type_used));
  j << ", \"linear_solver_ordering_used\": [";
  for (size_t g = 0; g < summary.linear_solver_ordering_used.size(); ++g)
    j << (g ? ", " : "") << summary.linear_solver_ordering_used[g];
  j << "]";
  j << ", \"schur_structure_used\": " << JsonString(summary.schur_structure_used);
  j << ", \"threads\": " << a.threads;
  j << ", \"num_threads_used\": " << summary.num_threads_used;
  j << ", \"termination\": "
    << JsonString(ceres::TerminationTypeToString(summary.termination_type));
  j << ", \"message\": " << JsonString(summary.message);
  j << ", \"iterations\": " << summary.iterations.size() - 1;
  j << ", \"successful_steps\": " << summary.num_successful_steps;
  j << ", \"unsuccessful_steps\": " << summary.num_unsuccessful_steps;
  j << ", \"residual_evaluations\": " << summary.num_residual_evaluations;
  j << ", \"jacobian_evaluations\": " << summary.num_jacobian_evaluations;
  j << ", \"linear_solves\": " << summary.num_linear_solves;
  j << ", \"initial_cost\": " << summary.initial_cost;
  j << ", \"final_cost\": " << summary.final_cost;
  j << ", \"num_residual_blocks\": " << summary.num_residual_blocks_reduced;
  j << ", \"num_parameters\": " << summary.num_effective_parameters_reduced;
  j << ", \"residual_blocks_wider_than_window\": " << n_wide;
  j << ", \"free_points\": " << n_free_points;
  j << ", \"read_s\": " << t_read - t_start;
  j << ", \"build_s\": " << t_built - t_read;
  j << ", \"build_cpu_s\": " << c_built - c_start;
  j << ", \"solve_s\": " << t_solved - t_built;
  j << ", \"solve_cpu_s\": " << c_solved - c_built;
  j << ", \"covariance_s\": " << t_cov;
  j << ", \"covariance_cpu_s\": " << c_cov;
  j << ", \"covariance_ok\": " << (cov_ok ? "true" : "false");
  j << ", \"total_s\": " << Seconds() - t_start;
  j << ", \"total_cpu_s\": " << CpuSeconds() - c_start;
  j << ", \"ceres_preprocessor_s\": " << summary.preprocessor_time_in_seconds;
  j << ", \"ceres_minimizer_s\": " << summary.minimizer_time_in_seconds;
  j << ", \"ceres_postprocessor_s\": " << summary.postprocessor_time_in_seconds;
  j << ", \"ceres_total_s\": " << summary.total_time_in_seconds;
  j << ", \"ceres_linear_solver_s\": " << summary.linear_solver_time_in_seconds;
  j << ", \"ceres_residual_evaluation_s\": " << summary.residual_evaluation_time_in_seconds;
  j << ", \"ceres_jacobian_evaluation_s\": " << summary.jacobian_evaluation_time_in_seconds;
  j << ", \"rss_start_mb\": " << rss_start;
  j << ", \"rss_built_mb\": " << rss_built;
  j << ", \"peak_rss_mb\": " << StatusMb("VmHWM");
  j << ", \"ceres_version\": " << JsonString(CERES_VERSION_STRING);
  j << "}";
  std::cout << j.str() << std::endl;
  return summary.IsSolutionUsable() ? 0 : 4;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return Run(Parse(argc, argv));
  } catch (const std::exception& e) {
    std::cerr << "linescan_ba: " << e.what() << "\n";
    return 2;
  }
}
