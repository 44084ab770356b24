"""Reading rl-zoo's ``"dict(...)"`` hyperparameter strings without ``eval``.

rl-zoo writes ``policy_kwargs`` as Python source, e.g.
``"dict(net_arch=dict(pi=[64, 64], vf=[64, 64]), activation_fn=nn.ReLU)"``, and evaluates it.
Evaluating a string from a YAML file, a ``--hp`` argument or a sweep file runs whatever it says
(``nn.__builtins__`` reaches ``__import__``). :func:`parse_zoo_value` walks the string's syntax
tree instead and accepts only

* literals: numbers (with a leading ``-``/``+``), strings, ``True``/``False``/``None``, lists,
  tuples and dicts of accepted values;
* ``dict(key=value, ...)`` with keyword arguments only;
* the activation classes of :data:`ACTIVATIONS`, written ``nn.<Name>`` or ``torch.nn.<Name>``.

Anything else (another name or attribute, a call of anything but ``dict``, subscripts,
operators, comprehensions, lambdas) is refused with a ``ValueError`` naming it.
"""

from __future__ import annotations

import ast
from typing import Any

__all__ = ["ACTIVATIONS", "parse_zoo_value"]

#: torch.nn activation classes a policy_kwargs string may name
ACTIVATIONS: tuple[str, ...] = ("ReLU", "Tanh", "ELU", "LeakyReLU", "GELU", "SiLU", "Sigmoid", "Softplus", "SELU",
                                "Mish", "Hardswish", "Hardtanh", "ReLU6", "CELU", "PReLU", "Identity")
_MAX_LENGTH = 10_000


def _activation(node: ast.Attribute, where: str) -> Any:
    import torch.nn as nn

    prefix = node.value
    ok_prefix = (isinstance(prefix, ast.Name) and prefix.id == "nn") or (
        isinstance(prefix, ast.Attribute) and prefix.attr == "nn" and isinstance(prefix.value, ast.Name)
        and prefix.value.id == "torch")
    if not ok_prefix or node.attr not in ACTIVATIONS:
        raise ValueError(f"{where}: {ast.unparse(node)!r} is not allowed: the only names allowed are nn.<activation> "
                         f"with <activation> one of {list(ACTIVATIONS)}")
    return getattr(nn, node.attr)


def _value(node: ast.AST, where: str) -> Any:
    if isinstance(node, ast.Constant) and (node.value is None or isinstance(node.value, (bool, int, float, str))):
        return node.value
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)) \
            and isinstance(node.operand, ast.Constant) and isinstance(node.operand.value, (int, float)) \
            and not isinstance(node.operand.value, bool):
        return -node.operand.value if isinstance(node.op, ast.USub) else node.operand.value
    if isinstance(node, ast.List):
        return [_value(e, where) for e in node.elts]
    if isinstance(node, ast.Tuple):
        return tuple(_value(e, where) for e in node.elts)
    if isinstance(node, ast.Dict):
        if any(k is None for k in node.keys):
            raise ValueError(f"{where}: '**' in a dict is not allowed")
        return {_value(k, where): _value(v, where) for k, v in zip(node.keys, node.values, strict=True)}
    if isinstance(node, ast.Call):
        if not (isinstance(node.func, ast.Name) and node.func.id == "dict"):
            raise ValueError(f"{where}: the call {ast.unparse(node.func)!r}(...) is not allowed: only dict(...)")
        if node.args or any(k.arg is None for k in node.keywords):
            raise ValueError(f"{where}: dict(...) takes keyword arguments only (key=value)")
        return {k.arg: _value(k.value, where) for k in node.keywords}
    if isinstance(node, ast.Attribute):
        return _activation(node, where)
    raise ValueError(f"{where}: {ast.unparse(node)!r} is not allowed: only literals, dict(...) and "
                     f"nn.<activation> are")


def parse_zoo_value(text: str, where: str = "value") -> Any:
    """The value an rl-zoo hyperparameter string stands for, parsed without running it.

    Args:
        text: e.g. ``"dict(net_arch=[64, 64], activation_fn=nn.Tanh)"``.
        where: what the string is (named in errors), e.g. ``"hyperparameter policy_kwargs"``.

    Raises:
        ValueError: not valid Python syntax, or anything but the accepted forms (named).
    """
    if not isinstance(text, str):
        raise TypeError(f"{where}={text!r} is invalid: must be a string")
    if len(text) > _MAX_LENGTH:
        raise ValueError(f"{where} is invalid: {len(text)} characters, at most {_MAX_LENGTH}")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError) as exc:
        raise ValueError(f"{where}={text!r} is not a valid expression: {exc.msg if hasattr(exc, 'msg') else exc}") \
            from None
    return _value(tree.body, f"{where}={text!r}")
