"""The device spine's host side (`uwbcl.focus.processing`): the kernel-signature parser and the launch checks,
without a device."""

from __future__ import annotations

import numpy as np
import pytest

from uwbcl.focus.processing import KernelArgumentError, _Launcher, parse_kernel_signatures

SNIPPET = """
/* a comment with a decoy: __kernel void not_a_kernel(int x) */
#ifdef USE_FP64
typedef double real_t;
#else
typedef float real_t;
#endif
typedef float2 cplx_t;
#define HELPER(R) \\
    (R) + 1

inline float helper(const float x) { return x; }

__kernel void scale(__global cplx_t *restrict s, __global const real_t *restrict gain, const int n,
                    const real_t step_hz, __local float *scratch, unsigned int flags) {
    s[0] = s[0];
}

kernel void empty(void) {}
"""


class _FakeArray:
    """What a launch needs of a device array: a dtype and a `data` handle."""

    def __init__(self, dtype):
        self.dtype = np.dtype(dtype)
        self.data = object()


def test_the_parser_reads_names_qualifiers_and_types_of_every_kernel_argument():
    sig = parse_kernel_signatures(SNIPPET, {"USE_FP64": ""})
    assert set(sig) == {"scale", "empty"}
    assert sig["empty"].args == ()
    s, gain, n, step, scratch, flags = sig["scale"].args
    assert (s.name, s.address, s.c_type, s.pointer, s.const) == ("s", "global", "float2", True, False)
    assert s.dtype == np.complex64
    assert (gain.name, gain.c_type, gain.pointer, gain.const) == ("gain", "double", True, True)
    assert gain.dtype == np.float64
    assert (n.name, n.address, n.pointer, n.dtype) == ("n", "private", False, np.int32)
    assert (step.name, step.dtype) == ("step_hz", np.float64)
    assert (scratch.address, scratch.dtype) == ("local", np.float32)
    assert (flags.c_type, flags.dtype) == ("uint", np.uint32)


def test_real_t_resolves_to_float_without_the_fp64_define():
    sig = parse_kernel_signatures(SNIPPET, {})
    assert sig["scale"].args[1].dtype == np.float32 and sig["scale"].args[3].dtype == np.float32


def test_an_if_expression_in_kernel_source_is_refused_rather_than_guessed():
    with pytest.raises(ValueError, match="#if"):
        parse_kernel_signatures("#if X > 1\n#endif\n__kernel void k(int n) {}")


def test_a_launch_converts_scalars_to_the_signature_types_in_signature_order():
    launcher = _Launcher(object(), parse_kernel_signatures(SNIPPET, {"USE_FP64": ""})["scale"])
    s, gain, scratch = _FakeArray(np.complex64), _FakeArray(np.float64), _FakeArray(np.float32)
    values = launcher.values({"step_hz": 2.5, "n": 7, "gain": gain, "s": s, "scratch": scratch, "flags": 1})
    assert values[0] is s.data and values[1] is gain.data and values[4] is scratch.data
    assert type(values[2]) is np.int32 and type(values[3]) is np.float64 and type(values[5]) is np.uint32


def test_a_launch_with_two_argument_names_swapped_is_refused_naming_the_kernel_and_the_argument():
    launcher = _Launcher(object(), parse_kernel_signatures(SNIPPET, {"USE_FP64": ""})["scale"])
    args = {"s": _FakeArray(np.complex64), "gain": _FakeArray(np.float64), "scratch": _FakeArray(np.float32),
            "flags": 0}
    with pytest.raises(KernelArgumentError, match=r"kernel scale: argument n \(int\)"):
        launcher.values({**args, "n": 2.5, "step_hz": 7})  # the scalars' names swapped
    with pytest.raises(KernelArgumentError, match=r"kernel scale: argument s \(pointer to float2\)"):
        launcher.values({**args, "n": 2, "step_hz": 7.0, "s": args["gain"], "gain": args["s"]})  # buffers


def test_a_launch_with_a_missing_or_unknown_argument_is_refused_with_both_named():
    launcher = _Launcher(object(), parse_kernel_signatures(SNIPPET, {})["scale"])
    with pytest.raises(KernelArgumentError, match="kernel scale: missing flags; unknown flag"):
        launcher.values({"s": _FakeArray(np.complex64), "gain": _FakeArray(np.float32), "n": 1,
                         "step_hz": 1.0, "scratch": _FakeArray(np.float32), "flag": 0})


def test_a_boolean_or_a_host_array_is_not_a_kernel_argument():
    launcher = _Launcher(object(), parse_kernel_signatures(SNIPPET, {})["scale"])
    args = {"s": _FakeArray(np.complex64), "gain": _FakeArray(np.float32), "n": 1, "step_hz": 1.0,
            "scratch": _FakeArray(np.float32), "flags": 0}
    with pytest.raises(KernelArgumentError, match="argument n"):
        launcher.values({**args, "n": True})
    with pytest.raises(KernelArgumentError, match="argument gain"):
        launcher.values({**args, "gain": np.zeros(3, np.float32)})
