"""A progress bar for long work in a terminal (rich): `with_progress(label, work)` calls
`work(progress)`, where `progress(result, done, total)` is the callback vinetwin's batch
functions (export, campaign, validate, capture, fusion) accept, and returns what `work` returns."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


def with_progress(label: str, work: Callable[[Callable[[Any, int, int], None]], T]) -> T:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()
    ) as bar:
        task = bar.add_task(label, total=None)

        def progress(result: object, done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        return work(progress)
