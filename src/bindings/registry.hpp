// How the binding's files add to qpnso._core: each area (a file src/bindings/<area>.cpp) defines
//   QPNSO_BINDING(<area>) { ... m.def(...) ... }
// and its functions appear in the submodule qpnso._core.<area>. core_module.cpp calls every registered area
// once, in name order, so no file lists the others.
#pragma once

#include <nanobind/nanobind.h>

#include <map>
#include <string>

namespace qpnso::bindings {

using Register = void (*)(nanobind::module_&);

/// The areas registered so far (name -> function), filled by QPNSO_BINDING's static objects before NB_MODULE.
std::map<std::string, Register>& areas();

struct Area {
  Area(const char* name, Register define) { areas().emplace(name, define); }
};

}  // namespace qpnso::bindings

#define QPNSO_BINDING(name)                                                                  \
  static void qpnso_binding_##name(nanobind::module_& m);                                    \
  static const ::qpnso::bindings::Area qpnso_area_##name(#name, &qpnso_binding_##name);      \
  static void qpnso_binding_##name(nanobind::module_& m)
