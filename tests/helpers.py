"""Helpers shared by the test files."""
import copy


def edited(spec: dict, path, value=None, delete: bool = False) -> dict:
    """A deep copy of the scene description `spec` with the entry at `path` (keys / indices) set to
    `value`, or deleted."""
    spec = copy.deepcopy(spec)
    node = spec
    for key in path[:-1]:
        node = node[key]
    if delete:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return spec
