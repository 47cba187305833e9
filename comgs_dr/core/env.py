"""Process environment set-up that must happen before Dr.Jit's LLVM backend starts."""
import glob
import os


def ensure_llvm_path() -> None:
    """Point Dr.Jit at libLLVM 19 when the user has not chosen a library.

    Dr.Jit 1.5 refuses Debian's LLVM 14 and aborts with 15/16 ("Cannot select
    fminimum"), which it would otherwise pick up first.
    """
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    for pattern in ("/usr/lib/*/libLLVM.so.19*", "/usr/lib/*/libLLVM-19.so",
                    "/usr/lib/llvm-19/lib/libLLVM*.so*"):
        hits = sorted(glob.glob(pattern))
        if hits:
            os.environ["DRJIT_LIBLLVM_PATH"] = hits[0]
            return
