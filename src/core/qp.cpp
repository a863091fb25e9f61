// The dense QP through ProxSuite's C++ API (header-only: compiled into libqpnso_core, nothing of the proxsuite
// wheel is needed at run time).
#include <Eigen/Core>
#include <proxsuite/config.hpp>
#include <proxsuite/proxqp/dense/dense.hpp>

#include <optional>
#include <sstream>

#include "qpnso/core.hpp"

#ifndef QPNSO_VERSION
#define QPNSO_VERSION "unknown"
#endif

namespace qpnso::core {

namespace {
using RowMajor = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using MapMat = Eigen::Map<const RowMajor>;
using MapVec = Eigen::Map<const Eigen::VectorXd>;
}  // namespace

std::string build_info() {
  std::ostringstream s;
  s << "qpnso " << QPNSO_VERSION << "; ProxSuite " << PROXSUITE_VERSION << "; Eigen " << EIGEN_WORLD_VERSION << '.'
    << EIGEN_MAJOR_VERSION << '.' << EIGEN_MINOR_VERSION << "; SIMD " << Eigen::SimdInstructionSetsInUse();
  return s.str();
}

QpResult solve_dense_qp(long n, long n_eq, long n_in, const double* H, const double* g, const double* A,
                        const double* b, const double* C, const double* l, const double* u, double eps_abs) {
  namespace pq = proxsuite::proxqp;
  // ProxSuite works on column-major matrices: the row-major inputs are copied once, here.
  const Eigen::MatrixXd Hc = MapMat(H, n, n);
  const Eigen::MatrixXd Ac = n_eq > 0 ? Eigen::MatrixXd(MapMat(A, n_eq, n)) : Eigen::MatrixXd(0, n);
  const Eigen::MatrixXd Cc = n_in > 0 ? Eigen::MatrixXd(MapMat(C, n_in, n)) : Eigen::MatrixXd(0, n);
  const Eigen::VectorXd gc = MapVec(g, n);
  const Eigen::VectorXd bc = n_eq > 0 ? Eigen::VectorXd(MapVec(b, n_eq)) : Eigen::VectorXd(0);
  const Eigen::VectorXd lc = n_in > 0 ? Eigen::VectorXd(MapVec(l, n_in)) : Eigen::VectorXd(0);
  const Eigen::VectorXd uc = n_in > 0 ? Eigen::VectorXd(MapVec(u, n_in)) : Eigen::VectorXd(0);

  pq::dense::QP<double> qp(n, n_eq, n_in);
  qp.settings.eps_abs = eps_abs;
  qp.settings.eps_rel = 0.0;
  qp.init(Hc, gc, Ac, bc, Cc, lc, uc);
  qp.solve();

  QpResult r;
  r.x.assign(qp.results.x.data(), qp.results.x.data() + qp.results.x.size());
  r.y.assign(qp.results.y.data(), qp.results.y.data() + qp.results.y.size());
  r.z.assign(qp.results.z.data(), qp.results.z.data() + qp.results.z.size());
  r.status = static_cast<int>(qp.results.info.status);
  r.iterations = static_cast<long>(qp.results.info.iter);
  r.primal_residual = qp.results.info.pri_res;
  r.dual_residual = qp.results.info.dua_res;
  return r;
}

}  // namespace qpnso::core
