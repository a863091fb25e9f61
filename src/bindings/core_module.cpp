// qpnso._core: the Python binding of the C++ core (nanobind). Arrays are read where NumPy keeps them when they
// are float64 and contiguous in the order asked (C order for QP matrices, CasADi's column-major for Function
// arguments: a 1-D array is both); anything else is converted once by nanobind. The C++ work runs without the GIL.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/vector.h>

#include <Python.h>

#include <stdexcept>
#include <string>
#include <vector>

#include "qpnso/core.hpp"
#include "registry.hpp"

namespace nb = nanobind;
using namespace nb::literals;
namespace core = qpnso::core;

using FIn = nb::ndarray<const double, nb::f_contig, nb::device::cpu>;
using FOut = nb::ndarray<double, nb::f_contig, nb::device::cpu>;
using FArg = nb::ndarray<double, nb::f_contig, nb::device::cpu>;  // a bound input: the caller writes it in place
using NpArray = nb::ndarray<nb::numpy, double>;

namespace {

NpArray new_fortran(long rows, long cols, double** data) {
  auto* owned = new std::vector<double>(static_cast<size_t>(rows * cols), 0.0);
  *data = owned->data();
  nb::capsule owner(owned, [](void* p) noexcept { delete static_cast<std::vector<double>*>(p); });
  const size_t shape[2] = {static_cast<size_t>(rows), static_cast<size_t>(cols)};
  const int64_t strides[2] = {1, rows};
  return NpArray(owned->data(), 2, shape, owner, strides);
}

void check(bool ok, const std::string& what) {
  if (!ok) throw nb::value_error(what.c_str());
}

std::vector<const double*> arguments(const core::CasadiFunction& f, const std::vector<FIn>& args) {
  check(static_cast<long>(args.size()) == f.n_in(),
        f.name() + " takes " + std::to_string(f.n_in()) + " arguments, got " + std::to_string(args.size()));
  std::vector<const double*> in(args.size());
  for (size_t i = 0; i < args.size(); ++i) {
    check(static_cast<long>(args[i].size()) == f.rows_in(i) * f.cols_in(i),
          f.name() + ": argument " + std::to_string(i) + " must have " + std::to_string(f.rows_in(i)) + " x " +
              std::to_string(f.cols_in(i)) + " elements");
    in[i] = args[i].data();
  }
  return in;
}

// A CasadiFunction's evaluation bound once to its argument and output arrays: a call converts nothing.
class Bound {
 public:
  Bound(core::CasadiFunction& f, std::vector<FArg> args, std::vector<FOut> outputs)
      : f_(f), args_(std::move(args)), outputs_(std::move(outputs)) {
    check(static_cast<long>(args_.size()) == f_.n_in(), f_.name() + ": wrong number of arguments");
    for (size_t i = 0; i < args_.size(); ++i) {
      check(static_cast<long>(args_[i].size()) == f_.rows_in(i) * f_.cols_in(i),
            f_.name() + ": argument " + std::to_string(i) + " has the wrong size");
      in_.push_back(args_[i].data());
    }
    check(static_cast<long>(outputs_.size()) == f_.n_out(), f_.name() + ": wrong number of outputs");
    for (size_t i = 0; i < outputs_.size(); ++i) {
      check(static_cast<long>(outputs_[i].size()) == f_.rows_out(i) * f_.cols_out(i),
            f_.name() + ": output " + std::to_string(i) + " has the wrong size");
      out_.push_back(outputs_[i].data());
    }
  }
  void call() {
    nb::gil_scoped_release released;
    f_.eval(in_.data(), out_.data());
  }

 private:
  core::CasadiFunction& f_;
  std::vector<FArg> args_;
  std::vector<FOut> outputs_;
  std::vector<const double*> in_;
  std::vector<double*> out_;
};

}  // namespace

std::map<std::string, qpnso::bindings::Register>& qpnso::bindings::areas() {
  static std::map<std::string, Register> registered;
  return registered;
}

NB_MODULE(_core, m) {
  for (const auto& [name, define] : qpnso::bindings::areas()) {
    nb::module_ sub = m.def_submodule(name.c_str());
    define(sub);
  }
  m.doc() = "qpnso's C++ core: CasADi Functions evaluated without Python (the tick's port: src/core/PORTING.md).";
  m.def("build_info", &core::build_info);
  // Whether the thread holds the GIL inside a call made the way the core's bindings make theirs.
  m.def("_gil_held_in_core_call", []() {
    nb::gil_scoped_release released;
    return PyGILState_Check() != 0;
  });

  nb::class_<core::CasadiFunction>(m, "CasadiFunction")
      .def_static("load_compiled", &core::CasadiFunction::load_compiled, "library"_a, "name"_a,
                  "A Function from the shared library compiled from casadi.Function.generate's C (dlopen).")
      .def_static("load_runtime", &core::CasadiFunction::load_runtime, "libcasadi"_a, "serialized_file"_a,
                  "name"_a, "A Function saved by Function.save, evaluated by libcasadi's C API (dlopen).")
      .def_prop_ro("name", &core::CasadiFunction::name)
      .def_prop_ro("runtime", &core::CasadiFunction::runtime)
      .def_prop_ro("n_in", &core::CasadiFunction::n_in)
      .def_prop_ro("n_out", &core::CasadiFunction::n_out)
      .def(
          "__call__",
          [](core::CasadiFunction& f, const std::vector<FIn>& args) {
            std::vector<const double*> in = arguments(f, args);
            std::vector<double*> out(f.n_out());
            nb::list results;
            for (long i = 0; i < f.n_out(); ++i) results.append(new_fortran(f.rows_out(i), f.cols_out(i), &out[i]));
            {
              nb::gil_scoped_release released;
              f.eval(in.data(), out.data());
            }
            return results;
          },
          "args"_a, "The outputs, as new column-major arrays of the outputs' shapes.")
      .def(
          "eval_into",
          [](core::CasadiFunction& f, const std::vector<FIn>& args, std::vector<FOut> outputs) {
            std::vector<const double*> in = arguments(f, args);
            check(static_cast<long>(outputs.size()) == f.n_out(), f.name() + ": wrong number of outputs");
            std::vector<double*> out(outputs.size());
            for (size_t i = 0; i < outputs.size(); ++i) {
              check(static_cast<long>(outputs[i].size()) == f.rows_out(i) * f.cols_out(i),
                    f.name() + ": output " + std::to_string(i) + " has the wrong size");
              out[i] = outputs[i].data();
            }
            nb::gil_scoped_release released;
            f.eval(in.data(), out.data());
          },
          "args"_a, "outputs"_a.noconvert(),
          "Writes the outputs into the given float64 column-major arrays (no allocation, no copy).")
      .def(
          "bind",
          [](core::CasadiFunction& f, std::vector<FArg> args, std::vector<FOut> outputs) {
            return Bound(f, std::move(args), std::move(outputs));
          },
          "args"_a.noconvert(), "outputs"_a.noconvert(), nb::keep_alive<0, 1>(),
          "An evaluation bound to these float64 column-major arrays, read and written where they lie on each call "
          "(a tick's: no argument to convert). The Bound keeps the arrays and the function alive.");

  nb::class_<Bound>(m, "Bound").def("__call__", &Bound::call, "Evaluates from the bound inputs into the bound outputs.");
}
