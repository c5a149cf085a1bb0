"""The events of a step in time order: a binary heap over an (capacity, 5) float array, compiled.

A row is (time, sequence number, contact, stamp of its first body, stamp of its second); rows
are ordered by time, then sequence (ties first in, first out, so the order does not depend on
anything but the schedule). Stale rows are not removed: the event loop drops a popped row whose
stamps no longer match its bodies'.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def heap_push(heap, size, t, seq, c, stamp_a, stamp_b):
    """Push an event (time, sequence, contact, stamps) on the binary heap; returns (heap, size)."""
    if size == heap.shape[0]:
        bigger = np.empty((2 * size + 16, 5))
        bigger[:size] = heap[:size]
        heap = bigger
    i = size
    heap[i, 0], heap[i, 1], heap[i, 2], heap[i, 3], heap[i, 4] = t, seq, c, stamp_a, stamp_b
    while i > 0:
        parent = (i - 1) // 2
        if heap[i, 0] < heap[parent, 0] or (heap[i, 0] == heap[parent, 0] and heap[i, 1] < heap[parent, 1]):
            for d in range(5):
                heap[i, d], heap[parent, d] = heap[parent, d], heap[i, d]
            i = parent
        else:
            break
    return heap, size + 1


@njit(cache=True)
def heap_pop(heap, size):
    """The earliest event: (time, contact, stamp_a, stamp_b, new size)."""
    t, c, sa, sb = heap[0, 0], int(heap[0, 2]), int(heap[0, 3]), int(heap[0, 4])
    size -= 1
    if size > 0:
        for d in range(5):
            heap[0, d] = heap[size, d]
        i = 0
        while True:
            left, smallest = 2 * i + 1, i
            for child in (left, left + 1):
                if child < size and (heap[child, 0] < heap[smallest, 0] or (
                        heap[child, 0] == heap[smallest, 0] and heap[child, 1] < heap[smallest, 1])):
                    smallest = child
            if smallest == i:
                break
            for d in range(5):
                heap[i, d], heap[smallest, d] = heap[smallest, d], heap[i, d]
            i = smallest
    return t, c, sa, sb, size
