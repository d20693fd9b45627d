// stereorepro._core: optional native kernels. Pure torch / numpy (stereorepro/*.py) is the reference;
// every kernel has a Python twin and a parity test (tests/reproject/test_reproject_native.py,
// tests/reproject/test_fast_clamp.py, tests/render/test_render_native.py).
#include <nanobind/nanobind.h>

namespace nb = nanobind;

void bind_info(nb::module_ &m);
void bind_reproject(nb::module_ &m);
void bind_shade_tracer(nb::module_ &m);

NB_MODULE(_core, m) {
    m.doc() = "stereorepro native CPU kernels (optional accelerator; torch is the reference)";
    bind_info(m);
    bind_reproject(m);
    bind_shade_tracer(m);
}
