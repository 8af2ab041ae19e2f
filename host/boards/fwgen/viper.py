"""AST transforms that turn a readable firmware method into its native or viper build.

The firmware's per-tick code is written once, as plain methods (``Controller.step``,
``Sensors.update``, ``Supervisor.update``, ``Motor.duty``, ``Timing.begin``/``end``).  This
module reads such a method with :mod:`ast` and rewrites it for MicroPython's emitters:

* :func:`native_function`: the method as a module-level ``@micropython.native`` function of
  its object (``self.x`` -> ``c.x``);
* :func:`object_viper_function`: ``@micropython.viper`` on an object whose int32 arrays are
  read through ``ptr32`` (every load sign-extended, right on 32- and 64-bit ports) and whose
  int attributes are read as ``int(c.x)`` (``Controller.step``);
* :func:`slot_viper_function`: ``@micropython.viper`` on a slot array: the object's per-tick
  attributes are slots of one ``array('i')`` (the layout: :mod:`host.boards.fwgen.layout`),
  loads and stores become ``S[_XX_NAME]`` (signed slots sign-extended), flags 0/1, chained
  comparisons split, attributes outside the layout passed as extra ``int`` arguments, calls
  named in ``inline`` expanded from a template (``Timing``'s tick difference).

The sign extension ``((v + sb) & msk) - sb`` uses ``sb = 1 << 31`` built at run time (a
folded ``2**31`` would be a big-int constant on a 32-bit target).
"""

from __future__ import annotations

import ast
import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping

__all__ = [
    "SIGN_PRELUDE",
    "SlotObject",
    "module_consts",
    "find_method",
    "native_function",
    "object_viper_function",
    "slot_viper_function",
    "referenced_names",
    "unparse",
]

# the three statements every viper function with sign extension starts with
SIGN_PRELUDE = "sb = 1\nsb = sb << 31\nmsk = sb | (sb - 1)\n"


def _group(op: ast.operator) -> str:
    if isinstance(op, (ast.Add, ast.Sub)):
        return "add"
    if isinstance(op, (ast.Mult, ast.FloorDiv, ast.Mod, ast.Div)):
        return "mul"
    if isinstance(op, (ast.LShift, ast.RShift)):
        return "shift"
    return type(op).__name__


class _Unparser(ast._Unparser):  # type: ignore[name-defined,misc]
    # ast.unparse with the parentheses a reader expects: an operand that is itself a binary
    # operation of another group (shifts and bit operations mixed with arithmetic, or with
    # each other) or a boolean operation of the other kind is parenthesised, whatever the
    # precedence; products inside sums and sums inside sums are not
    def require_parens(self, precedence, node):  # noqa: ANN001, ANN201 - ast._Unparser's signature
        return self.delimit_if("(", ")", getattr(node, "_paren", False) or self.get_precedence(node) > precedence)

    def visit_BinOp(self, node: ast.BinOp) -> None:
        for side in (node.left, node.right):
            if isinstance(side, ast.BinOp) and _group(side.op) != _group(node.op) and not (
                    _group(side.op) == "mul" and _group(node.op) == "add"):
                side._paren = True  # type: ignore[attr-defined]
        super().visit_BinOp(node)

    def visit_BoolOp(self, node: ast.BoolOp) -> None:
        for v in node.values:
            if isinstance(v, ast.BoolOp) and type(v.op) is not type(node.op):
                v._paren = True  # type: ignore[attr-defined]
        super().visit_BoolOp(node)


def unparse(node: ast.AST) -> str:
    """Source text of an AST, with explicit parentheses around mixed operators."""
    return _Unparser().visit(node)


def _parse(path: Path) -> ast.Module:
    return ast.parse(path.read_text(), filename=str(path))


def _const_value(node: ast.expr) -> int | None:
    """The int an expression of literals folds to (``const(...)`` unwrapped), else None."""
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "const" and len(node.args) == 1:
        node = node.args[0]
    if any(isinstance(n, (ast.Name, ast.Attribute, ast.Call)) for n in ast.walk(node)):
        return None
    try:
        v = eval(compile(ast.Expression(body=node), "<const>", "eval"), {"__builtins__": {}})
    except Exception:  # noqa: BLE001 - anything that is not a literal int expression
        return None
    return v if isinstance(v, int) and not isinstance(v, bool) else None


def module_consts(path: Path) -> dict[str, int]:
    """Module-level ``NAME = const(int)`` / ``NAME = int`` assignments of a firmware module.

    Parameters
    ----------
    path : Path
        The firmware module's source.

    Returns
    -------
    dict of str to int
        Name -> value, in source order.
    """
    out: dict[str, int] = {}
    for node in _parse(path).body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            v = _const_value(node.value)
            if v is not None:
                out[node.targets[0].id] = v
    return out


def find_method(path: Path, cls: str, name: str) -> ast.FunctionDef:
    """The ``def name`` of class ``cls`` in a module, as a fresh AST (a copy).

    Raises
    ------
    ValueError
        When the class or the method is missing.
    """
    for node in _parse(path).body:
        if isinstance(node, ast.ClassDef) and node.name == cls:
            for item in node.body:
                if isinstance(item, ast.FunctionDef) and item.name == name:
                    return copy.deepcopy(item)
            raise ValueError(f"{path.name}: class {cls} has no method {name}")
    raise ValueError(f"{path.name}: no class {cls}")


def referenced_names(fn: ast.AST) -> set[str]:
    """Every bare name an AST loads (to pick the module constants a function needs)."""
    return {n.id for n in ast.walk(fn) if isinstance(n, ast.Name)}


def _strip_docs(body: list[ast.stmt]) -> list[ast.stmt]:
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str):
        return body[1:]
    return body


def _self_attr(node: ast.AST, me: str = "self") -> str | None:
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == me:
        return node.attr
    return None


def _sign_ext(expr: ast.expr) -> ast.expr:
    # ((expr + sb) & msk) - sb
    inner = ast.BinOp(ast.BinOp(expr, ast.Add(), ast.Name("sb", ast.Load())), ast.BitAnd(), ast.Name("msk", ast.Load()))
    out = ast.BinOp(inner, ast.Sub(), ast.Name("sb", ast.Load()))
    out._paren = True  # type: ignore[attr-defined]  # read as one value
    return out


def _decorator(kind: str) -> ast.expr:
    return ast.Attribute(ast.Name("micropython", ast.Load()), kind, ast.Load())


def _arg(name: str, ann: str | None) -> ast.arg:
    return ast.arg(arg=name, annotation=ast.Name(ann, ast.Load()) if ann else None)


def _function(name: str, args: list[ast.arg], body: list[ast.stmt], kind: str, returns: str | None) -> ast.FunctionDef:
    fn = ast.FunctionDef(
        name=name,
        args=ast.arguments(posonlyargs=[], args=args, vararg=None, kwonlyargs=[], kw_defaults=[], kwarg=None, defaults=[]),
        body=body,
        decorator_list=[_decorator(kind)],
        returns=ast.Name(returns, ast.Load()) if returns else None,
    )
    return ast.fix_missing_locations(fn)


class _Rename(ast.NodeTransformer):
    # self -> the object's name
    def __init__(self, old: str, new: str) -> None:
        self.old, self.new = old, new

    def visit_Name(self, node: ast.Name) -> ast.Name:
        if node.id == self.old:
            return ast.copy_location(ast.Name(self.new, node.ctx), node)
        return node


def native_function(method: ast.FunctionDef, name: str, obj: str = "c") -> ast.FunctionDef:
    """The method as ``@micropython.native def name(obj, ...)``: the same body on ``obj``."""
    body = [_Rename("self", obj).visit(s) for s in _strip_docs(copy.deepcopy(method.body))]
    args = [_arg(obj, None)] + [_arg(a.arg, None) for a in method.args.args[1:]]
    return _function(name, args, body, "native", None)


class _ObjectViper(ast.NodeTransformer):
    # Controller.step's rewrite: `a = self.a` for an int32 array -> `a = ptr32(c.a)` (a is then
    # a pointer local whose loads are sign-extended); loads of int attributes -> int(c.x)
    def __init__(self, obj: str, arrays: set[str], scalars: set[str]) -> None:
        self.obj, self.arrays, self.scalars = obj, arrays, scalars
        self.ptrs: set[str] = set()

    def visit_Assign(self, node: ast.Assign) -> ast.Assign:
        a = _self_attr(node.value)
        if len(node.targets) == 1 and isinstance(node.targets[0], ast.Name) and a in self.arrays:
            self.ptrs.add(node.targets[0].id)
            call = ast.Call(ast.Name("ptr32", ast.Load()), [ast.Attribute(ast.Name(self.obj, ast.Load()), a, ast.Load())], [])
            return ast.copy_location(ast.Assign(node.targets, call), node)
        node.value = self.visit(node.value)
        node.targets = [self.visit(t) for t in node.targets]
        return node

    def visit_Attribute(self, node: ast.Attribute) -> ast.expr:
        a = _self_attr(node)
        if a is None:
            return self.generic_visit(node)
        attr = ast.Attribute(ast.Name(self.obj, ast.Load()), a, node.ctx)
        if isinstance(node.ctx, ast.Load) and a in self.scalars:
            return ast.Call(ast.Name("int", ast.Load()), [attr], [])
        return attr

    def visit_Subscript(self, node: ast.Subscript) -> ast.expr:
        node.slice = self.visit(node.slice)
        if isinstance(node.value, ast.Name) and node.value.id in self.ptrs and isinstance(node.ctx, ast.Load):
            return _sign_ext(node)
        node.value = self.visit(node.value)
        return node


def object_viper_function(method: ast.FunctionDef, name: str, arrays: Iterable[str], scalars: Iterable[str],
                          obj: str = "c", returns: str = "int") -> ast.FunctionDef:
    """The method as ``@micropython.viper def name(obj, x: int, ...) -> int`` (see module doc).

    Raises
    ------
    ValueError
        When an array attribute is used other than bound once to a local (``a = self.a``),
        or ``self`` is left in the result.
    """
    t = _ObjectViper(obj, set(arrays), set(scalars))
    body = [t.visit(s) for s in _strip_docs(copy.deepcopy(method.body))]
    args = [_arg(obj, None)] + [_arg(a.arg, "int") for a in method.args.args[1:]]
    fn = _function(name, args, ast.parse(SIGN_PRELUDE).body + body, "viper", returns)
    for n in ast.walk(fn):
        if isinstance(n, ast.Name) and n.id == "self":
            raise ValueError(f"{name}: the transform left a reference to self")
        if isinstance(n, ast.Attribute) and n.attr in t.arrays and not (
                isinstance(n.value, ast.Name) and n.value.id == obj):
            raise ValueError(f"{name}: array {n.attr} used other than bound to a local")
    return fn


@dataclass(frozen=True)
class SlotObject:
    """One object's per-tick state as slots of an ``array('i')`` (declared in the layout).

    Attributes
    ----------
    prefix : str
        The slot constants' prefix (``"SN"`` -> ``_SN_POS``).
    slots : tuple of (str, str)
        Attribute name and kind, in slot order: ``"i"`` a signed int (its loads
        sign-extended), ``"u"`` a non-negative int, ``"b"`` a flag (a bool attribute, 0/1).
    """

    prefix: str
    slots: tuple[tuple[str, str], ...]
    kinds: dict[str, str] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "kinds", dict(self.slots))

    def const(self, attr: str) -> str:
        """The slot index constant's name of an attribute (``_pos`` -> ``_SN_POS``)."""
        return f"_{self.prefix}_{attr.strip('_').upper()}"

    @property
    def size_const(self) -> str:
        """The name of the constant holding the number of slots."""
        return f"_{self.prefix}_SLOTS"


def _is_boolish(node: ast.expr) -> bool:
    return isinstance(node, (ast.Compare, ast.BoolOp)) or (isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not))


class _SlotViper(ast.NodeTransformer):
    def __init__(self, arr: str, obj: SlotObject, inline: Mapping[str, str], consts: set[str]) -> None:
        self.arr, self.obj, self.inline, self.consts = arr, obj, dict(inline), consts
        self.extra: list[str] = []  # attributes outside the layout, read -> extra arguments
        self.bool_return = False

    def _slot(self, attr: str, ctx: ast.expr_context) -> ast.expr:
        sub = ast.Subscript(ast.Name(self.arr, ast.Load()), ast.Name(self.obj.const(attr), ast.Load()), ctx)
        if isinstance(ctx, ast.Load) and self.obj.kinds[attr] == "i":
            return _sign_ext(sub)
        return sub

    def visit_Attribute(self, node: ast.Attribute) -> ast.expr:
        a = _self_attr(node)
        if a is None:
            return self.generic_visit(node)
        if a in self.obj.kinds:
            return self._slot(a, node.ctx)
        if not isinstance(node.ctx, ast.Load):
            raise ValueError(f"store to self.{a}, which is not in the slot layout")
        if a not in self.extra:
            self.extra.append(a)
        return ast.Name(a, ast.Load())

    def visit_Compare(self, node: ast.Compare) -> ast.expr:
        # a < b < c -> a < b and b < c (the operands are simple: no double evaluation matters)
        node = self.generic_visit(node)
        if len(node.ops) == 1:
            return node
        parts, left = [], node.left
        for op, right in zip(node.ops, node.comparators):
            parts.append(ast.Compare(left, [op], [right]))
            left = right
        return ast.BoolOp(ast.And(), parts)

    def visit_Constant(self, node: ast.Constant) -> ast.expr:
        if isinstance(node.value, bool):
            return ast.copy_location(ast.Constant(1 if node.value else 0), node)
        return node

    def visit_Return(self, node: ast.Return) -> ast.Return:
        if isinstance(node.value, ast.Constant) and isinstance(node.value.value, bool):
            self.bool_return = True
        node = self.generic_visit(node)
        if node.value is not None and _is_boolish(node.value):
            # a comparison returned: 1/0 (a viper function returns one type)
            node.value = ast.IfExp(node.value, ast.Constant(1), ast.Constant(0))
        return node

    def _store(self, attr: str, value: ast.expr, like: ast.stmt) -> list[ast.stmt]:
        if self.obj.kinds[attr] == "b" and _is_boolish(value):
            s = ast.If(value, [ast.Assign([self._slot(attr, ast.Store())], ast.Constant(1))],
                       [ast.Assign([self._slot(attr, ast.Store())], ast.Constant(0))])
        else:
            s = ast.Assign([self._slot(attr, ast.Store())], value)
        return [ast.copy_location(s, like)]

    def visit_Assign(self, node: ast.Assign) -> list[ast.stmt] | ast.stmt:
        if len(node.targets) == 1:
            tgt = node.targets[0]
            a = _self_attr(tgt)
            call = node.value
            if isinstance(tgt, ast.Name) and isinstance(call, ast.Call) and _self_attr(call.func) in self.inline:
                return self._inline(tgt.id, call, node)
            if a in self.obj.kinds:
                return self._store(a, self.visit(node.value), node)
        return self.generic_visit(node)

    def visit_AugAssign(self, node: ast.AugAssign) -> list[ast.stmt] | ast.stmt:
        a = _self_attr(node.target)
        if a in self.obj.kinds:
            load = ast.Attribute(ast.Name("self", ast.Load()), a, ast.Load())
            value = self.visit(ast.BinOp(load, node.op, node.value))
            return self._store(a, value, node)
        return self.generic_visit(node)

    def _inline(self, target: str, call: ast.Call, like: ast.stmt) -> list[ast.stmt]:
        name = _self_attr(call.func)
        args = [self.visit(a) for a in call.args]
        tpl = ast.parse(self.inline[name]).body
        subst = {"out": target, **{f"a{i}": a for i, a in enumerate(args)}}

        class _Fill(ast.NodeTransformer):
            def visit_Name(self, n: ast.Name) -> ast.expr:
                v = subst.get(n.id)
                if v is None:
                    return n
                if isinstance(v, str):
                    return ast.Name(v, n.ctx)
                return copy.deepcopy(v)

        out = [ast.copy_location(_Fill().visit(s), like) for s in tpl]
        self.consts |= referenced_names(ast.Module(body=tpl, type_ignores=[]))
        return out


def slot_viper_function(method: ast.FunctionDef, name: str, obj: SlotObject, arr: str = "S",
                        inline: Mapping[str, str] | None = None) -> tuple[ast.FunctionDef, list[str], bool, set[str]]:
    """The method as ``@micropython.viper def name(S: ptr32, x: int, ..., extra: int)``.

    Parameters
    ----------
    method : ast.FunctionDef
        The readable method (from :func:`find_method`).
    name : str
        The generated function's name.
    obj : SlotObject
        The slot layout of the method's object.
    arr : str
        The slot array argument's name.
    inline : mapping of str to str, optional
        ``self.<method>(a0, a1)`` assigned to a local ``out`` -> these statements (names
        ``out``, ``a0``, ``a1`` … substituted).

    Returns
    -------
    tuple
        The function, the extra arguments (attributes outside the layout, in order), whether
        it returns a flag (``True``/``False`` in the source: 1/0 here) and the names the
        inlined templates use.
    """
    used: set[str] = set()
    t = _SlotViper(arr, obj, inline or {}, used)
    body: list[ast.stmt] = []
    for s in _strip_docs(copy.deepcopy(method.body)):
        r = t.visit(s)
        body.extend(r if isinstance(r, list) else [r])
    fn = ast.Module(body=body, type_ignores=[])
    signed = any(isinstance(n, ast.Name) and n.id == "sb" for n in ast.walk(fn))
    returns_value = any(isinstance(n, ast.Return) and n.value is not None for n in ast.walk(fn))
    args = [_arg(arr, "ptr32")] + [_arg(a.arg, "int") for a in method.args.args[1:]] + [_arg(e, "int") for e in t.extra]
    pre = ast.parse(SIGN_PRELUDE).body if signed else []
    f = _function(name, args, pre + body, "viper", "int" if returns_value else None)
    for n in ast.walk(f):
        if isinstance(n, ast.Name) and n.id == "self":
            raise ValueError(f"{name}: the transform left a reference to self")
    return f, t.extra, t.bool_return, used


class _MethodViper(ast.NodeTransformer):
    # a method kept a method (or a helper's): int attributes of named objects read as int(o.x),
    # int-returning calls wrapped in int(), `x = o.a` for an int32 array a -> a ptr32 local
    # (`x is not None` on it taken as true: the build is made only for an array), module
    # constants `M.NAME` -> the private const `_NAME`, True/False -> 1/0, a comparison stored
    # in a local -> 1/0
    def __init__(self, ints: Mapping[str, set[str]], calls: Mapping[str, set[str]], arrays: Mapping[str, set[str]],
                 modules: Mapping[str, dict[str, int]]) -> None:
        self.ints, self.calls, self.arrays, self.modules = ints, calls, arrays, modules
        self.ptrs: set[str] = set()
        self.consts: dict[str, int] = {}

    def _obj_attr(self, node: ast.AST) -> tuple[str, str] | None:
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            return node.value.id, node.attr
        return None

    def visit_Attribute(self, node: ast.Attribute) -> ast.expr:
        oa = self._obj_attr(node)
        if oa and oa[0] in self.modules and oa[1] in self.modules[oa[0]]:
            name = _private_name(oa[1])
            self.consts[name] = self.modules[oa[0]][oa[1]]
            return ast.copy_location(ast.Name(name, ast.Load()), node)
        node = self.generic_visit(node)
        if oa and isinstance(node.ctx, ast.Load) and oa[1] in self.ints.get(oa[0], ()):
            return ast.Call(ast.Name("int", ast.Load()), [node], [])
        return node

    def visit_Call(self, node: ast.Call) -> ast.expr:
        oa = self._obj_attr(node.func)
        node.args = [self.visit(a) for a in node.args]
        if oa and oa[1] in self.calls.get(oa[0], ()):
            return ast.Call(ast.Name("int", ast.Load()), [node], [])
        return node

    def visit_Constant(self, node: ast.Constant) -> ast.expr:
        if isinstance(node.value, bool):
            return ast.copy_location(ast.Constant(1 if node.value else 0), node)
        return node

    def visit_Assign(self, node: ast.Assign) -> ast.stmt:
        tgt = node.targets[0] if len(node.targets) == 1 else None
        oa = self._obj_attr(node.value)
        if isinstance(tgt, ast.Name) and oa and oa[1] in self.arrays.get(oa[0], ()):
            self.ptrs.add(tgt.id)
            return ast.copy_location(ast.Assign([tgt], ast.Call(ast.Name("ptr32", ast.Load()), [node.value], [])), node)
        value = self.visit(node.value)
        if isinstance(tgt, ast.Name) and _is_boolish(value):
            return ast.copy_location(ast.If(value, [ast.Assign([tgt], ast.Constant(1))],
                                            [ast.Assign([copy.deepcopy(tgt)], ast.Constant(0))]), node)
        node.value = value
        node.targets = [self.visit(t) for t in node.targets]
        return node

    def visit_If(self, node: ast.If) -> ast.stmt | list[ast.stmt]:
        t = node.test
        if (isinstance(t, ast.Compare) and len(t.ops) == 1 and isinstance(t.ops[0], ast.IsNot)
                and isinstance(t.left, ast.Name) and t.left.id in self.ptrs
                and isinstance(t.comparators[0], ast.Constant) and t.comparators[0].value is None):
            out: list[ast.stmt] = []
            for s in node.body:
                r = self.visit(s)
                out.extend(r if isinstance(r, list) else [r])
            return out
        return self.generic_visit(node)

    def visit_Subscript(self, node: ast.Subscript) -> ast.expr:
        node.slice = self.visit(node.slice)
        if isinstance(node.value, ast.Name) and node.value.id in self.ptrs and isinstance(node.ctx, ast.Load):
            return _sign_ext(node)
        node.value = self.visit(node.value)
        return node


def _private_name(name: str) -> str:
    return name if name.startswith("_") else "_" + name


def method_viper(method: ast.FunctionDef, ints: Mapping[str, Iterable[str]], calls: Mapping[str, Iterable[str]] | None = None,
                 arrays: Mapping[str, Iterable[str]] | None = None, modules: Mapping[str, dict[str, int]] | None = None,
                 self_as: str | None = None, consts: Mapping[str, int] | None = None,
                 ) -> tuple[ast.FunctionDef, dict[str, int]]:
    """A method rewritten as a ``@micropython.viper`` method (see :class:`_MethodViper`).

    Parameters
    ----------
    method : ast.FunctionDef
        The readable method.
    ints : mapping of str to names
        Local or ``self`` name -> its attributes that hold small ints.
    calls : mapping of str to names, optional
        Object name -> its methods that return small ints.
    arrays : mapping of str to names, optional
        Object name -> its int32 array attributes (read through ``ptr32``).
    modules : mapping of str to dict, optional
        Module alias -> its constants (``T.P_TELEM_DIV`` -> ``_P_TELEM_DIV``).
    self_as : str, optional
        The method belongs to another object reached as ``self.<self_as>`` (a helper built
        around it): ``self`` in the source becomes that name, bound first.
    consts : mapping of str to int, optional
        Module constants of the source, renamed to their private names.

    Returns
    -------
    tuple
        The method and the private constants it uses (name -> value).
    """
    t = _MethodViper({k: set(v) for k, v in ints.items()}, {k: set(v) for k, v in (calls or {}).items()},
                     {k: set(v) for k, v in (arrays or {}).items()}, modules or {})
    src = copy.deepcopy(method)
    body = _strip_docs(src.body)
    if self_as is not None:
        body = [_Rename("self", self_as).visit(s) for s in body]
    out: list[ast.stmt] = []
    for s in body:
        r = t.visit(s)
        out.extend(r if isinstance(r, list) else [r])
    used = dict(t.consts)
    if consts:
        names = referenced_names(ast.Module(body=out, type_ignores=[]))
        ren = {k for k in consts if k in names}
        for k in ren:
            used[_private_name(k)] = consts[k]

        class _Priv(ast.NodeTransformer):
            def visit_Name(self, n: ast.Name) -> ast.Name:
                return ast.Name(_private_name(n.id), n.ctx) if n.id in ren else n

        out = [_Priv().visit(s) for s in out]
    if any(isinstance(n, ast.Name) and n.id == "sb" for s in out for n in ast.walk(s)):
        out = ast.parse(SIGN_PRELUDE).body + out
    if self_as is not None:
        out = [ast.Assign([ast.Name(self_as, ast.Store())], ast.Attribute(ast.Name("self", ast.Load()), self_as,
                                                                         ast.Load()))] + out
    returns_value = any(isinstance(n, ast.Return) and n.value is not None for s in out for n in ast.walk(s))
    args = [_arg("self", None)] + [_arg(a.arg, "int") for a in method.args.args[1:]]
    return _function(method.name, args, out, "viper", "int" if returns_value else None), used


def prelude(ptrs: tuple[str, ...] = ("ptr32",)) -> str:
    """The import block a generated native/viper module starts with: ``micropython`` and ``const``
    from the port, or under CPython the stand-ins of ``firmware/viperstub.py`` (no-op decorators,
    ``const`` the identity, the pointer casts ``ptrs`` of ``ptr8``/``ptr16``/``ptr32`` as plain
    indexing) -- one module, not a copy in each generated file."""
    bad = [p for p in ptrs if p not in ("ptr8", "ptr16", "ptr32")]
    if bad:
        raise ValueError(f"no CPython stand-in for {bad}")
    names = ", ".join(("micropython", "const", *ptrs))
    return ("try:\n    import micropython\n    from micropython import const\n"
            f"except ImportError:  # CPython\n    from .viperstub import {names}\n")
