// qpnso's C++ core: the public API, for the Python binding (qpnso._core) and for C++ programs
// (find_package(qpnso) against an installed wheel: examples/cpp/).
//
// This header names no Eigen, ProxSuite or CasADi type: a program that uses it needs only this header and
// libqpnso_core, whatever Eigen or ProxSuite it has (they are compiled into the library). Matrices are dense,
// row-major (C order, NumPy's default), so a NumPy array is read where it lies.
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <vector>

#if defined(_WIN32)
#define QPNSO_CORE_API __declspec(dllimport)
#else
#define QPNSO_CORE_API __attribute__((visibility("default")))
#endif

namespace qpnso::core {

/// The versions compiled into the library: qpnso's, ProxSuite's headers', Eigen's, and Eigen's SIMD sets.
QPNSO_CORE_API std::string build_info();

/// A CasADi Function evaluated without Python, through CasADi's C calling convention, on either
///  * a shared library compiled from the C that casadi.Function.generate wrote (dlopen; no libcasadi), or
///  * CasADi's own runtime: libcasadi from the casadi wheel, dlopen'ed at run time, a Function saved with
///    Function.save loaded and evaluated through libcasadi's C API (casadi_c.h).
/// Neither links casadi at build time. Inputs and outputs are dense, column-major (CasADi's order); sparse
/// patterns are scattered/gathered here. Work memory is allocated when loaded: eval allocates nothing.
class QPNSO_CORE_API CasadiFunction {
 public:
  static CasadiFunction load_compiled(const std::string& library, const std::string& name);
  static CasadiFunction load_runtime(const std::string& libcasadi, const std::string& serialized_file,
                                     const std::string& name);
  CasadiFunction(CasadiFunction&&) noexcept;
  CasadiFunction& operator=(CasadiFunction&&) noexcept;
  ~CasadiFunction();

  const std::string& name() const;
  const char* runtime() const;  ///< "compiled C" or "casadi runtime"
  long n_in() const;
  long n_out() const;
  long rows_in(long i) const;
  long cols_in(long i) const;
  long rows_out(long i) const;
  long cols_out(long i) const;
  /// in[i]: rows_in(i)*cols_in(i) doubles; out[i]: rows_out(i)*cols_out(i) doubles (null: not wanted).
  void eval(const double* const* in, double* const* out);

 private:
  struct Impl;
  explicit CasadiFunction(std::unique_ptr<Impl>);
  std::unique_ptr<Impl> impl_;
};

}  // namespace qpnso::core
