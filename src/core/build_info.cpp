// What the core was built with (qpnso::core::build_info): qpnso's version, the ProxSuite and Eigen headers
// compiled in, the SIMD instruction sets Eigen uses (the generic x86-64 target: SSE, SSE2).
#include <Eigen/Core>
#include <proxsuite/config.hpp>

#include <sstream>

#include "qpnso/core.hpp"

#ifndef QPNSO_VERSION
#define QPNSO_VERSION "unknown"
#endif

namespace qpnso::core {

std::string build_info() {
  std::ostringstream s;
  s << "qpnso " << QPNSO_VERSION << "; ProxSuite " << PROXSUITE_VERSION << "; Eigen " << EIGEN_WORLD_VERSION << '.'
    << EIGEN_MAJOR_VERSION << '.' << EIGEN_MINOR_VERSION << "; SIMD " << Eigen::SimdInstructionSetsInUse();
  return s.str();
}

}  // namespace qpnso::core
