// The same solve_dense_qp as qpnso._core.solve_dense_qp, called from C++ with no Python:
// min 1/2 x'Hx + g'x  s.t.  x0 + x1 + x2 = 1,  -0.4 <= x <= 1.
#include <qpnso/core.hpp>

#include <cstdio>

int main() {
  const double H[9] = {4.0, 1.0, 0.0, 1.0, 3.0, 0.5, 0.0, 0.5, 2.0};
  const double g[3] = {1.0, -2.0, 0.5};
  const double A[3] = {1.0, 1.0, 1.0}, b[1] = {1.0};
  const double C[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1}, l[3] = {-0.4, -0.4, -0.4}, u[3] = {1.0, 1.0, 1.0};
  const qpnso::core::QpResult r = qpnso::core::solve_dense_qp(3, 1, 3, H, g, A, b, C, l, u);
  std::printf("%s\nstatus %d, %ld iterations\nx = %.17g %.17g %.17g\n", qpnso::core::build_info().c_str(), r.status,
              r.iterations, r.x[0], r.x[1], r.x[2]);
  return r.status == 0 ? 0 : 1;
}
