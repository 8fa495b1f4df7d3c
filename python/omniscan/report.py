"""Reports of the stages: the library's serde reports as Python objects."""

from __future__ import annotations

import json
from typing import Any, Iterator


class Report:
    """A stage's report: the fields of the library's report struct as
    attributes (nested reports as Reports, lists as lists), ``r["key"]`` as
    well, and :meth:`to_dict` for the plain JSON values. ``kind`` names the
    stage that made it."""

    __slots__ = ("_data", "kind")

    def __init__(self, data: dict, kind: str = "") -> None:
        object.__setattr__(self, "_data", data)
        object.__setattr__(self, "kind", kind)

    @staticmethod
    def _wrap(value: Any) -> Any:
        if isinstance(value, dict):
            return Report(value)
        if isinstance(value, list):
            return [Report._wrap(v) for v in value]
        return value

    def __getattr__(self, name: str) -> Any:
        try:
            return Report._wrap(self._data[name])
        except KeyError:
            raise AttributeError(
                f"this {self.kind or 'report'} has no field {name!r}; it has {sorted(self._data)}"
            ) from None

    def __getitem__(self, key: str) -> Any:
        return Report._wrap(self._data[key])

    def __contains__(self, key: object) -> bool:
        return key in self._data

    def __iter__(self) -> Iterator[str]:
        return iter(self._data)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("a report is read-only")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Report) and self._data == other._data

    def __dir__(self) -> list:
        return sorted(set(self._data) | {"to_dict", "to_json", "kind"})

    def keys(self) -> list:
        return list(self._data)

    def to_dict(self) -> dict:
        """The report as plain JSON values (a deep copy)."""
        return json.loads(json.dumps(self._data))

    def to_json(self, indent: int = 2) -> str:
        """The report as the command line's ``--json`` prints it."""
        return json.dumps(self._data, indent=indent)

    def __repr__(self) -> str:
        kind = f"{self.kind} " if self.kind else ""
        return f"<{kind}report {json.dumps(self._data)[:200]}>"
