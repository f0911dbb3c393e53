"""Taichi's front end with its source reads and source-position strings memoised: the same text, once a process.

Before Taichi can look a kernel up in its offline cache it turns the kernel's Python AST into its IR,
and for every statement and expression it builds it formats where that node sits in the source (the
file, the line and a caret line under the node, each wrapped by ``textwrap``) for its error messages
and the IR's debug information. The same node is built over and over: a ``ti.func`` at every call that
inlines it, a static loop's body once per unrolled iteration (3^d stencil nodes). In the first step of
shake_container_2d that formatting was about half of the front end's time (cProfile), and the front end
runs in every process, from the cache too. ``memoise_front_end`` keeps each distinct string: the key
holds everything Taichi's formatting reads (the function's file, line offset, indent and name; the
node's type and coordinates; a block's first body line), so the text, the IR and its cache key are
unchanged. Likewise each function's source lines (``inspect.getsourcelines`` tokenises the whole
function), which the front end read again at every inlining of a ``ti.func``.
"""

import functools

from taichi.lang import kernel_impl
from taichi.lang.ast import ast_transformer_utils

_Context = ast_transformer_utils.ASTTransformerContext
_taichi_get_pos_info = _Context.get_pos_info
_positions: dict[tuple, str] = {}


def _get_pos_info(ctx, node) -> str:
    body = getattr(node, "body", None)
    key = (
        ctx.file,
        ctx.lineno_offset,
        ctx.indent,
        ctx.func.func.__name__,
        type(node).__name__,
        node.lineno,
        node.end_lineno,
        node.col_offset,
        node.end_col_offset,
        body[0].lineno if isinstance(body, list) and body else None,
    )
    info = _positions.get(key)
    if info is None:
        info = _positions[key] = _taichi_get_pos_info(ctx, node)
    return info


def memoise_front_end() -> None:
    """Have Taichi's front end read each function's source and format each node's source position once (in
    place of Taichi's own functions only: a second call, or a test's wrapper, is left as it is)."""
    if _Context.get_pos_info is _taichi_get_pos_info:
        _Context.get_pos_info = _get_pos_info
    for name in ("getsourcelines", "getsourcefile"):
        read = getattr(kernel_impl, name)
        if not hasattr(read, "cache_info"):  # a function's source does not change while the process runs
            setattr(kernel_impl, name, functools.lru_cache(maxsize=None)(read))


def taichi_positions(ctx, node) -> str:
    """Taichi's own formatting of ``node``'s position, not memoised (tests compare the two)."""
    return _taichi_get_pos_info(ctx, node)
