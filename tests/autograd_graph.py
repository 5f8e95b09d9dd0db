"""Test helper: what an autograd graph holds."""

from __future__ import annotations

import torch


def count_nodes(tensor: torch.Tensor, name: str) -> int:
    """How many nodes of ``tensor``'s autograd graph have ``name`` in their type's name."""
    seen, stack, count = set(), [tensor.grad_fn], 0
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        count += name in type(node).__name__
        stack.extend(next_fn for next_fn, _ in node.next_functions)
    return count
