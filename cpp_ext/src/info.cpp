#include <nanobind/nanobind.h>
#include <nanobind/stl/string.h>
#ifdef STEREOREPRO_OPENMP
#include <omp.h>
#endif

namespace nb = nanobind;

void bind_info(nb::module_ &m) {
    m.def("build_info", []() {
        nb::dict d;
#ifdef STEREOREPRO_OPENMP
        d["openmp"] = true;
        d["max_threads"] = omp_get_max_threads();
#else
        d["openmp"] = false;
        d["max_threads"] = 1;
#endif
        d["compiler"] = std::string(__VERSION__);
        return d;
    }, "Compile-time facts about the native core: OpenMP, thread count, compiler.");
}
