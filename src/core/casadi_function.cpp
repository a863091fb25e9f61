// CasADi Functions evaluated without Python, through CasADi's C calling convention (the one of the code
// casadi.Function.generate writes, and the one of libcasadi's C API, casadi_c.h). Both are dlopen'ed at run
// time: libqpnso_core links neither casadi nor a generated library, so it needs no casadi at build time and
// runs beside whichever casadi the user has.
#include <dlfcn.h>

#include <algorithm>
#include <map>
#include <cstring>
#include <mutex>
#include <stdexcept>
#include <string>
#include <vector>

#include "qpnso/core.hpp"

namespace qpnso::core {

namespace {
using casadi_int = long long;  // CasADi's default (codegen option casadi_int, casadi_c_int_width())

// A dense pattern is stored compressed as {nrow, ncol, 1}; any other as {nrow, ncol, colind[ncol+1], row[nnz]}
// (colind[0] is then 0).
struct Pattern {
  long rows = 0, cols = 0;
  bool dense = true;
  std::vector<long> colind, row;
  long nnz() const { return dense ? rows * cols : colind.back(); }
  static Pattern from(const casadi_int* sp) {
    Pattern p;
    p.rows = static_cast<long>(sp[0]);
    p.cols = static_cast<long>(sp[1]);
    p.dense = sp[2] == 1 || p.rows * p.cols == 0;  // colind[0] == 0 when not compressed
    if (!p.dense) {
      p.colind.assign(sp + 2, sp + 3 + p.cols);
      p.row.assign(sp + 3 + p.cols, sp + 3 + p.cols + p.colind.back());
      if (static_cast<long>(p.row.size()) == p.rows * p.cols) p.dense = true;  // stored in full, not compressed
    }
    return p;
  }
};

template <class F>
F symbol(void* handle, const std::string& name, bool required = true) {
  dlerror();
  void* s = dlsym(handle, name.c_str());
  if (s == nullptr && required) {
    const char* e = dlerror();
    throw std::runtime_error("CasADi function: no symbol " + name + (e ? std::string(": ") + e : std::string()));
  }
  return reinterpret_cast<F>(s);
}

std::recursive_mutex runtime_mutex;  // libcasadi's C API keeps one global list of loaded Functions: not thread-safe
// (recursive: an Impl released while load_runtime unwinds takes it again)

// Which entries of libcasadi's list (by id, per loaded libcasadi) a live CasadiFunction still uses. The C API
// can only pop the list's last entry, so a released Function's entry is popped once every entry above it is
// released too: without this, each load kept its Function (about 1 MB for a tick's state function) for good.
std::map<void*, std::vector<bool>>& runtime_live() {
  static std::map<void*, std::vector<bool>> live;
  return live;
}

// Pops the dead entries at the top of libcasadi's list (runtime_mutex held).
void pop_released(void* handle) {
  std::vector<bool>& live = runtime_live()[handle];
  auto n_loaded = symbol<int (*)()>(handle, "casadi_c_n_loaded");
  auto pop = symbol<int (*)()>(handle, "casadi_c_pop");
  while (!live.empty() && !live.back() && n_loaded() == static_cast<int>(live.size())) {
    pop();
    live.pop_back();
  }
}
}  // namespace

struct CasadiFunction::Impl {
  std::string name;
  bool runtime = false;
  void* handle = nullptr;
  int id = -1, mem = 0;
  // the generated code's entry points
  int (*f)(const double**, double**, casadi_int*, double*, int) = nullptr;
  void (*release)(int) = nullptr;
  void (*decref)() = nullptr;
  // libcasadi's
  int (*f_id)(int, const double**, double**, casadi_int*, double*, int) = nullptr;
  void (*release_id)(int, int) = nullptr;
  void (*decref_id)(int) = nullptr;

  std::vector<Pattern> in, out;
  std::vector<const double*> arg;
  std::vector<double*> res;
  std::vector<casadi_int> iw;
  std::vector<double> w;
  std::vector<std::vector<double>> nz_in, nz_out;  // for sparse patterns only

  void setup(casadi_int n_in, casadi_int n_out, casadi_int sz_arg, casadi_int sz_res, casadi_int sz_iw,
             casadi_int sz_w) {
    arg.assign(std::max<casadi_int>(sz_arg, n_in), nullptr);
    res.assign(std::max<casadi_int>(sz_res, n_out), nullptr);
    iw.assign(std::max<casadi_int>(sz_iw, 1), 0);
    w.assign(std::max<casadi_int>(sz_w, 1), 0.0);
    nz_in.resize(in.size());
    nz_out.resize(out.size());
    for (size_t i = 0; i < in.size(); ++i)
      if (!in[i].dense) nz_in[i].assign(in[i].nnz(), 0.0);
    for (size_t i = 0; i < out.size(); ++i)
      if (!out[i].dense) nz_out[i].assign(out[i].nnz(), 0.0);
  }

  ~Impl() {
    if (runtime) {
      std::lock_guard<std::recursive_mutex> lock(runtime_mutex);
      if (release_id) release_id(id, mem);
      if (decref_id) decref_id(id);
      if (id >= 0) {
        runtime_live()[handle].at(id) = false;
        pop_released(handle);
      }
    } else {
      if (release) release(mem);
      if (decref) decref();
    }
    if (handle) dlclose(handle);
  }
};

CasadiFunction::CasadiFunction(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
CasadiFunction::CasadiFunction(CasadiFunction&&) noexcept = default;
CasadiFunction& CasadiFunction::operator=(CasadiFunction&&) noexcept = default;
CasadiFunction::~CasadiFunction() = default;

CasadiFunction CasadiFunction::load_compiled(const std::string& library, const std::string& name) {
  auto p = std::make_unique<Impl>();
  p->name = name;
  p->handle = dlopen(library.c_str(), RTLD_NOW | RTLD_LOCAL);
  if (!p->handle) throw std::runtime_error("CasADi function: cannot load " + library + ": " + dlerror());
  p->f = symbol<decltype(p->f)>(p->handle, name);
  auto work = symbol<int (*)(casadi_int*, casadi_int*, casadi_int*, casadi_int*)>(p->handle, name + "_work");
  auto n_in = symbol<casadi_int (*)()>(p->handle, name + "_n_in");
  auto n_out = symbol<casadi_int (*)()>(p->handle, name + "_n_out");
  auto sp_in = symbol<const casadi_int* (*)(casadi_int)>(p->handle, name + "_sparsity_in");
  auto sp_out = symbol<const casadi_int* (*)(casadi_int)>(p->handle, name + "_sparsity_out");
  auto incref = symbol<void (*)()>(p->handle, name + "_incref", false);
  auto checkout = symbol<int (*)()>(p->handle, name + "_checkout", false);
  p->release = symbol<void (*)(int)>(p->handle, name + "_release", false);
  p->decref = symbol<void (*)()>(p->handle, name + "_decref", false);
  if (incref) incref();
  p->mem = checkout ? checkout() : 0;
  const casadi_int ni = n_in(), no = n_out();
  for (casadi_int i = 0; i < ni; ++i) p->in.push_back(Pattern::from(sp_in(i)));
  for (casadi_int i = 0; i < no; ++i) p->out.push_back(Pattern::from(sp_out(i)));
  casadi_int sz_arg = 0, sz_res = 0, sz_iw = 0, sz_w = 0;
  if (work(&sz_arg, &sz_res, &sz_iw, &sz_w)) throw std::runtime_error("CasADi function: " + name + "_work failed");
  p->setup(ni, no, sz_arg, sz_res, sz_iw, sz_w);
  return CasadiFunction(std::move(p));
}

CasadiFunction CasadiFunction::load_runtime(const std::string& libcasadi, const std::string& serialized_file,
                                            const std::string& name) {
  std::lock_guard<std::recursive_mutex> lock(runtime_mutex);
  auto p = std::make_unique<Impl>();
  p->name = name;
  p->runtime = true;
  p->handle = dlopen(libcasadi.c_str(), RTLD_NOW | RTLD_LOCAL);
  if (!p->handle) throw std::runtime_error("CasADi runtime: cannot load " + libcasadi + ": " + dlerror());
  auto h = p->handle;
  auto int_width = symbol<int (*)()>(h, "casadi_c_int_width");
  if (int_width() != static_cast<int>(sizeof(casadi_int)))
    throw std::runtime_error("CasADi runtime: casadi_int is not 64 bits in " + libcasadi);
  auto push_file = symbol<int (*)(const char*)>(h, "casadi_c_push_file");
  auto n_loaded = symbol<int (*)()>(h, "casadi_c_n_loaded");
  auto name_id = symbol<const char* (*)(int)>(h, "casadi_c_name_id");
  // Look the name up among the Functions this file added: two files may hold Functions of the same name.
  const int before = n_loaded();
  if (push_file(serialized_file.c_str()))
    throw std::runtime_error("CasADi runtime: cannot read Functions from " + serialized_file);
  const int after = n_loaded();
  std::vector<bool>& live = runtime_live()[h];
  if (static_cast<int>(live.size()) < before) live.resize(before, true);  // (pushed by others: never popped)
  live.resize(after, false);  // (entries of the file other than ours are released at once)
  for (int i = before; i < after && p->id < 0; ++i)
    if (name == name_id(i)) p->id = i;
  if (p->id < 0) {
    pop_released(h);
    throw std::runtime_error("CasADi runtime: no Function " + name + " in " + serialized_file);
  }
  live[p->id] = true;
  const int id = p->id;
  p->f_id = symbol<decltype(p->f_id)>(h, "casadi_c_eval_id");
  p->release_id = symbol<void (*)(int, int)>(h, "casadi_c_release_id");
  p->decref_id = symbol<void (*)(int)>(h, "casadi_c_decref_id");
  symbol<void (*)(int)>(h, "casadi_c_incref_id")(id);
  p->mem = symbol<int (*)(int)>(h, "casadi_c_checkout_id")(id);
  auto n_in = symbol<casadi_int (*)(int)>(h, "casadi_c_n_in_id");
  auto n_out = symbol<casadi_int (*)(int)>(h, "casadi_c_n_out_id");
  auto sp_in = symbol<const casadi_int* (*)(int, casadi_int)>(h, "casadi_c_sparsity_in_id");
  auto sp_out = symbol<const casadi_int* (*)(int, casadi_int)>(h, "casadi_c_sparsity_out_id");
  auto work = symbol<int (*)(int, casadi_int*, casadi_int*, casadi_int*, casadi_int*)>(h, "casadi_c_work_id");
  const casadi_int ni = n_in(id), no = n_out(id);
  for (casadi_int i = 0; i < ni; ++i) p->in.push_back(Pattern::from(sp_in(id, i)));
  for (casadi_int i = 0; i < no; ++i) p->out.push_back(Pattern::from(sp_out(id, i)));
  casadi_int sz_arg = 0, sz_res = 0, sz_iw = 0, sz_w = 0;
  if (work(id, &sz_arg, &sz_res, &sz_iw, &sz_w)) throw std::runtime_error("CasADi runtime: work sizes failed");
  p->setup(ni, no, sz_arg, sz_res, sz_iw, sz_w);
  return CasadiFunction(std::move(p));
}

const std::string& CasadiFunction::name() const { return impl_->name; }
const char* CasadiFunction::runtime() const { return impl_->runtime ? "casadi runtime" : "compiled C"; }
long CasadiFunction::n_in() const { return static_cast<long>(impl_->in.size()); }
long CasadiFunction::n_out() const { return static_cast<long>(impl_->out.size()); }
long CasadiFunction::rows_in(long i) const { return impl_->in.at(i).rows; }
long CasadiFunction::cols_in(long i) const { return impl_->in.at(i).cols; }
long CasadiFunction::rows_out(long i) const { return impl_->out.at(i).rows; }
long CasadiFunction::cols_out(long i) const { return impl_->out.at(i).cols; }

void CasadiFunction::eval(const double* const* in, double* const* out) {
  Impl& p = *impl_;
  for (size_t i = 0; i < p.in.size(); ++i) {
    const Pattern& s = p.in[i];
    if (s.dense || in[i] == nullptr) {
      p.arg[i] = in[i];
      continue;
    }
    for (long c = 0; c < s.cols; ++c)
      for (long k = s.colind[c]; k < s.colind[c + 1]; ++k) p.nz_in[i][k] = in[i][s.row[k] + c * s.rows];
    p.arg[i] = p.nz_in[i].data();
  }
  for (size_t i = 0; i < p.out.size(); ++i)
    p.res[i] = (p.out[i].dense || out[i] == nullptr) ? out[i] : p.nz_out[i].data();
  const int flag = p.runtime ? p.f_id(p.id, p.arg.data(), p.res.data(), p.iw.data(), p.w.data(), p.mem)
                             : p.f(p.arg.data(), p.res.data(), p.iw.data(), p.w.data(), p.mem);
  if (flag) throw std::runtime_error("CasADi function " + p.name + " failed (" + std::to_string(flag) + ")");
  for (size_t i = 0; i < p.out.size(); ++i) {
    const Pattern& s = p.out[i];
    if (s.dense || out[i] == nullptr) continue;
    std::fill(out[i], out[i] + s.rows * s.cols, 0.0);
    for (long c = 0; c < s.cols; ++c)
      for (long k = s.colind[c]; k < s.colind[c + 1]; ++k) out[i][s.row[k] + c * s.rows] = p.nz_out[i][k];
  }
}

}  // namespace qpnso::core
