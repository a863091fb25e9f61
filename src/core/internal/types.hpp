// The core's Eigen types (src/core/PORTING.md): dynamic sizes only; row-major matrices where they mirror a
// NumPy record's field (C order), so a record's memory can be mapped where it lies.
#pragma once

#include <Eigen/Core>

namespace qpnso::core {

using Index = Eigen::Index;
using Vector = Eigen::VectorXd;
using RowMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using Matrix = Eigen::MatrixXd;

}  // namespace qpnso::core
