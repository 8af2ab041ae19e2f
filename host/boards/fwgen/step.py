"""``App.step`` rewritten for viper: ``fasttick.StepV``, generated from the plain step.

The plain step (``firmware/app.py``) reads the sensors, supervises, runs the controller and
drives the motor through the app's parts.  In the viper build (:func:`step_class`):

* the parts with a slot layout (:data:`host.boards.fwgen.layout.TICK_PARTS`: ``self.timing``,
  ``self.sensors``, ``self.sup``, ``self.motor``) are reached through their slot arrays, cached
  on the ``StepV`` helper at construction: their generated methods become calls of the viper
  functions on the array (``tm.begin(t0)`` -> ``timing_begin(tm_o, t0)``), their attributes
  ``ptr32`` loads and stores, other methods calls on the object (``s.zero()``);
* ``self`` is the app (``app = self.app``); the app's, the controller's and the HAL's int
  attributes and int-returning methods (:data:`STEP`) are read through ``int()``;
* conditions on what the HAL offers (fixed at construction: :data:`STEP` ``"fixed"``) are bits
  of one int computed once (``opts``), tested per tick without an attribute load;
* ``if a and b:`` becomes nested ifs (viper does not mix an int and an object in ``and``).
"""

from __future__ import annotations

import ast
from typing import Any

from host.boards.fwgen.layout import FIRMWARE, STEP, TICK_PARTS, TickPart
from host.boards.fwgen.viper import SIGN_PRELUDE, _function, _sign_ext, find_method, module_consts, unparse

__all__ = ["step_class"]


def _path(node: ast.AST) -> str | None:
    # "self.hal" for Attribute(Name self, hal); "c" for Name c
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        p = _path(node.value)
        return f"{p}.{node.attr}" if p else None
    return None


class _Step(ast.NodeTransformer):
    def __init__(self, parts: dict[str, tuple[TickPart, dict[str, str], dict[str, tuple[list[str], bool]]]],
                 spec: dict[str, Any], consts: dict[str, int]) -> None:
        self.parts = parts  # self.<attr> -> (part, method -> function, function -> (extras, returns))
        self.ints = {k: set(v) for k, v in spec["ints"].items()}
        self.calls = {k: set(v) for k, v in spec["calls"].items()}
        self.arrays = {k: set(v) for k, v in spec["arrays"].items()}
        self.int_locals = set(spec["int_locals"])
        self.fixed = [ast.dump(ast.parse(e, mode="eval").body) for e in spec["fixed"]]
        self.consts = consts
        self.used: dict[str, int] = {}
        self.locals: dict[str, str] = {}  # local name -> the self attribute of its part
        self.cached: list[str] = []  # parts whose array/object StepV caches
        self.bound: set[str] = set()  # parts whose array is in a local (_a_<attr>, _p_<attr>)

    # ---- helpers ----
    def _part_of(self, node: ast.AST) -> str | None:
        # the part attribute an expression names: a local bound to it or self.<attr>
        if isinstance(node, ast.Name) and node.id in self.locals:
            return self.locals[node.id]
        p = _path(node)
        if p and p.startswith("self.") and p[5:] in self.parts:
            return p[5:]
        return None

    def _cache(self, attr: str) -> None:
        if attr not in self.cached:
            self.cached.append(attr)

    def _arr(self, attr: str) -> ast.expr:
        # the slot array object (for calls) of a part: its local once bound, else the cached one
        if attr in self.bound:
            return ast.Name(f"_a_{attr}", ast.Load())
        self._cache(attr)
        return ast.Attribute(ast.Name("self", ast.Load()), f"_S_{attr}", ast.Load())

    def _obj(self, attr: str) -> ast.expr:
        self._cache(attr)
        return ast.Attribute(ast.Name("self", ast.Load()), f"_o_{attr}", ast.Load())

    def _ptr(self, attr: str) -> str:
        return f"_p_{attr}"

    @staticmethod
    def _int(node: ast.expr) -> ast.expr:
        return ast.Call(ast.Name("int", ast.Load()), [node], [])

    # ---- statements ----
    def visit_Assign(self, node: ast.Assign) -> Any:
        tgt = node.targets[0] if len(node.targets) == 1 else None
        p = _path(node.value)
        if isinstance(tgt, ast.Name) and p and p.startswith("self.") and p[5:] in self.parts:
            # `tm = self.timing`: the part's array as a ptr32 local (its object stays cached)
            # (the array object in a local too: the generated functions take it as an object)
            attr = p[5:]
            self.locals[tgt.id] = attr
            arr = self._arr(attr)
            self.bound.add(attr)
            return [ast.copy_location(ast.Assign([ast.Name(f"_a_{attr}", ast.Store())], arr), node),
                    ast.copy_location(ast.Assign([ast.Name(self._ptr(attr), ast.Store())],
                                                 ast.Call(ast.Name("ptr32", ast.Load()), [ast.Name(f"_a_{attr}", ast.Load())],
                                                          [])), node)]
        if isinstance(tgt, ast.Attribute):
            attr = self._part_of(tgt.value)
            if attr is not None:
                part = self.parts[attr][0]
                if tgt.attr in part.state.kinds:
                    sub = ast.Subscript(ast.Name(self._ptr(attr), ast.Load()),
                                        ast.Name(part.state.const(tgt.attr), ast.Load()), ast.Store())
                    self._need_ptr(attr)
                    return ast.copy_location(ast.Assign([sub], self.visit(node.value)), node)
        return self.generic_visit(node)

    def _need_ptr(self, attr: str) -> None:
        self._cache(attr)
        self.ptr_used = getattr(self, "ptr_used", set()) | {attr}

    def visit_If(self, node: ast.If) -> Any:
        t = node.test
        if isinstance(t, ast.BoolOp) and isinstance(t.op, ast.And) and not node.orelse:
            inner = ast.If(t.values[-1] if len(t.values) == 2 else ast.BoolOp(ast.And(), t.values[1:]), node.body, [])
            outer = ast.If(t.values[0], [inner], [])
            return self.visit(ast.copy_location(outer, node))
        return self.generic_visit(node)

    # ---- expressions ----
    def visit_Compare(self, node: ast.Compare) -> Any:
        return self._fixed(node) or self.generic_visit(node)

    def _fixed(self, node: ast.expr) -> ast.expr | None:
        d = ast.dump(node)
        if d in self.fixed:
            bit = 1 << self.fixed.index(d)
            return ast.BinOp(ast.Name("opts", ast.Load()), ast.BitAnd(), ast.Constant(bit))
        return None

    def visit_Attribute(self, node: ast.Attribute) -> Any:
        f = self._fixed(node)
        if f is not None:
            return f
        attr = self._part_of(node.value)
        if attr is not None and isinstance(node.ctx, ast.Load):
            part = self.parts[attr][0]
            if node.attr in part.state.kinds:
                self._need_ptr(attr)
                sub = ast.Subscript(ast.Name(self._ptr(attr), ast.Load()), ast.Name(part.state.const(node.attr), ast.Load()),
                                    ast.Load())
                return _sign_ext(sub) if part.state.kinds[node.attr] == "i" else sub
            return ast.Attribute(self._obj(attr), node.attr, ast.Load())
        p = _path(node.value)
        new = self.generic_visit(node)
        if isinstance(node.ctx, ast.Load) and p is not None and node.attr in self.ints.get(p, ()):
            return self._int(new)
        return new

    def visit_Subscript(self, node: ast.Subscript) -> Any:
        # c.p[2] for a controller array: a ptr32 load, sign-extended
        p = _path(node.value)
        if isinstance(node.ctx, ast.Load) and isinstance(node.value, ast.Attribute) and p is not None:
            owner = _path(node.value.value)
            if owner is not None and node.value.attr in self.arrays.get(owner, ()):
                ptr = ast.Call(ast.Name("ptr32", ast.Load()), [node.value], [])
                return _sign_ext(ast.Subscript(ptr, self.visit(node.slice), ast.Load()))
        return self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> Any:
        node.args = [self.visit(a) for a in node.args]
        if isinstance(node.func, ast.Name) and node.func.id in self.int_locals:
            return self._int(node)
        if isinstance(node.func, ast.Attribute):
            attr = self._part_of(node.func.value)
            if attr is not None:
                part, funcs, info = self.parts[attr]
                if node.func.attr in funcs:
                    fname = funcs[node.func.attr]
                    extras, returns = info[fname]
                    args = [self._arr(attr), *node.args]
                    args += [ast.Attribute(self._obj(attr), e, ast.Load()) for e in extras]
                    call = ast.Call(ast.Name(fname, ast.Load()), args, [])
                    return self._int(call) if returns else call
                return ast.Call(ast.Attribute(self._obj(attr), node.func.attr, ast.Load()), node.args, [])
            p = _path(node.func.value)
            if p is not None and node.func.attr in self.calls.get(p, ()):
                return self._int(node)
        return node

    def visit_Name(self, node: ast.Name) -> Any:
        if node.id in self.consts:
            name = node.id if node.id.startswith("_") else "_" + node.id
            self.used[name] = self.consts[node.id]
            return ast.copy_location(ast.Name(name, node.ctx), node)
        return node


def step_class(parts_funcs: dict[str, tuple[dict[str, str], dict[str, tuple[list[str], bool]]]]) -> tuple[str, dict[str, int]]:
    """The text of ``class StepV`` and the private constants it uses.

    Parameters
    ----------
    parts_funcs : dict
        Part class name -> (method -> generated function, function -> (extra arguments,
        returns a value)), as the tick parts were generated.
    """
    by_attr = {}
    for attr, cls in STEP["parts"].items():
        part = next(p for p in TICK_PARTS if p.cls == cls)
        funcs, info = parts_funcs[cls]
        by_attr[attr] = (part, funcs, info)
    consts = {**module_consts(FIRMWARE / "supervisor.py"), **module_consts(FIRMWARE / "app.py")}
    src = find_method(FIRMWARE / "app.py", "App", "step")
    t = _Step(by_attr, STEP, consts)
    body: list[ast.stmt] = []
    for s in src.body:
        r = t.visit(s)
        body.extend(r if isinstance(r, list) else [r])
    # self is the app; the parts' ptr32 views and opts first
    body = [_Rename_self_app().visit(s) for s in body]
    head = ast.parse(SIGN_PRELUDE + "app = self.app\nopts = int(self.opts)\n").body
    fn = _function("step", [ast.arg("self")], head + body, "viper", "int")
    fixed = " | ".join(f"({1 << i} if {e.replace('self.', 'app.')} else 0)" for i, e in enumerate(STEP["fixed"]))
    init = ["    def __init__(self, app):", "        self.app = app"]
    for attr in t.cached:
        init.append(f"        self._o_{attr} = app.{attr}")
        init.append(f"        self._S_{attr} = app.{attr}._S")
    init.append(f"        self.opts = {fixed}")
    text = ("class StepV:\n"
            "    # App.step for the viper emitter, generated from it (firmware/emitter.py sets app.step =\n"
            "    # StepV(app).step): the parts on their slot arrays, the app's state and hooks read from\n"
            "    # the app as App.step reads them; what the HAL offers fixed at construction (opts)\n"
            + "\n".join(init) + "\n\n    " + unparse(fn).replace("\n", "\n    ") + "\n")
    return text, t.used


class _Rename_self_app(ast.NodeTransformer):
    # the source's self (the app) -> app; the helper's own cached attributes stay on self
    def visit_Attribute(self, node: ast.Attribute) -> Any:
        if isinstance(node.value, ast.Name) and node.value.id == "self" and (
                node.attr.startswith("_S_") or node.attr.startswith("_o_")):
            return node
        return self.generic_visit(node)

    def visit_Name(self, node: ast.Name) -> Any:
        if node.id == "self":
            return ast.copy_location(ast.Name("app", node.ctx), node)
        return node
