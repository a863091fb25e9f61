// A real-time loop's first piece on qpnso's C++ API: the control tick's CasADi state function (the tool pose,
// Jacobian, mass matrix, gravity, costs and elbow angle of docs/method.md §7, one evaluation a tick), exported
// from Python with StateEvaluator.save and evaluated here with no Python and no allocation in the loop.
//
//   state_loop LIBCASADI FUNCTION_FILE NAME TICKS
// LIBCASADI: the casadi wheel's libcasadi (CasADi's own runtime); prints the evaluation time's median and 99th
// percentile (us) over TICKS ticks of a slow joint sweep, then the state at the last tick, one value a line.
#include <qpnso/core.hpp>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <vector>

int main(int argc, char** argv) {
  if (argc != 5) {
    std::fprintf(stderr, "usage: %s LIBCASADI FUNCTION_FILE NAME TICKS\n", argv[0]);
    return 2;
  }
  qpnso::core::CasadiFunction f = qpnso::core::CasadiFunction::load_runtime(argv[1], argv[2], argv[3]);
  const long ticks = std::atol(argv[4]);
  const long n_in = f.rows_in(0) * f.cols_in(0), n_out = f.rows_out(0) * f.cols_out(0);
  const long nq = (n_in - 12) / 2;  // the input is (q, dq, twist, twist_prev): 2 nq + 12 entries
  std::vector<double> input(n_in, 0.0), state(n_out, 0.0), seconds(ticks, 0.0);
  const double* in[] = {input.data()};
  double* out[] = {state.data()};
  for (long k = 0; k < ticks; ++k) {
    for (long i = 0; i < nq; ++i) input[i] = 0.3 * std::sin(1e-3 * k + i);  // q (rad): a slow sweep, 1 ms ticks
    const auto t0 = std::chrono::steady_clock::now();
    f.eval(in, out);
    seconds[k] = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }
  std::sort(seconds.begin(), seconds.end());
  std::printf("%s: %s, %ld ticks: median %.2f us, p99 %.2f us\n", f.name().c_str(), f.runtime(), ticks,
              1e6 * seconds[ticks / 2], 1e6 * seconds[(99 * ticks) / 100]);
  for (double v : state) std::printf("%.17g\n", v);
  return 0;
}
