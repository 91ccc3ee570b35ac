"""The tracking step replayed from CUDA graphs over static cache buffers: ``TorchBackend(...,
cuda_graph=GraphOptions(max_keyframes=32))``.

    backend = TorchBackend.from_pretrained("pi3", dtype="bfloat16", device="cuda",
                                           cuda_graph=GraphOptions(max_keyframes=32))
    backend.track(frame, mapped.cache)      # the first call per capacity captures (see below)
    backend.graph_report                    # GraphReport(captures=..., replays=..., eager=...)

Why: an eager step of a large network launches well over a thousand small kernels from Python,
and on a fast GPU the launches, not the arithmetic, set the frame rate. A CUDA graph replays
them all in one launch. A graph holds fixed shapes and fixed addresses, while the map's cache
changes length with every rebuild and is a new tensor after each one, so the step runs over a
``StaticCache``: K/V buffers owned by the runner with a fixed capacity (``max_keyframes``
keyframes, plus one scratch region for the query frames right after that capacity). Each map is
copied into those buffers once when it first appears (a device copy, dequantised if the map is
stored quantised), and a per-layer boolean key mask, read by the graph at every replay, hides the
slots that hold no keyframe (a map that fills the capacity gets its own graph without the mask:
PyTorch's flash attention kernel takes no mask, and the masked kernel is slower). Attention does not depend on where a key sits in the buffer (the
keys were rotated by RoPE before they were cached), so the step computes the eager step's
function; only float summation order and the attention kernel (a masked one) differ.

Capacities: by default one capacity of ``max_keyframes`` serves every map, so a growing map never
captures again: the first tracking call captures two graphs (the masked one and the one for a
map that fills the capacity; ``graph_report.captures`` has their seconds), and the step then
costs what a full map costs whatever the map's size. With ``ladder=True`` a pair is captured per
power-of-two keyframe count up to ``max_keyframes`` (1, 2, 4, ..., max), the smallest that holds
the map: the step follows the map's size, but the first frame after the map grows past a rung
waits for a capture (many steps; ``docs/gpu.md`` has the measurements). A map larger
than ``max_keyframes``, several query frames, a device that is not CUDA or a failed capture run
the eager step (``graph_report.eager`` counts them, ``errors`` says why).

The query frames' own K/V are copied back into the map cache's scratch after each replay (a
one-frame pass of a dense cache), as the eager step leaves them there: incremental keyframes adopt
them (``KVCache.adopt_scratch``).

One runner serves one model; calls are serialised by a lock (the buffers are shared), so the
tracking thread and a mapping worker's insertion passes may both use it.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, cast

import torch
from torch import nn

from kvtracker_sdk.errors import CacheError, ConfigError
from kvtracker_sdk.log import get_logger
from kvtracker_sdk.models.layers.cache_layout import CacheLayout

__all__ = ["GraphOptions", "GraphReport", "GraphTracking", "StaticCache", "capacity_ladder"]

_log = get_logger(__name__)


@dataclass(frozen=True)
class GraphOptions:
    """How the tracking step is captured (``TorchBackend(cuda_graph=...)``)."""

    max_keyframes: int = 32  # the static buffers' capacity; set it to the tracker's budget
    ladder: bool = False  # True: a graph per power-of-two capacity (work follows the map)
    warmup_calls: int = 2  # eager calls on a side stream before a capture (cuBLAS/cuDNN set-up)

    def __post_init__(self) -> None:
        if not isinstance(self.max_keyframes, int) or self.max_keyframes < 1:
            raise ConfigError(f"max_keyframes must be an integer >= 1, got {self.max_keyframes!r}")
        if self.warmup_calls < 1:
            raise ConfigError(f"warmup_calls must be >= 1, got {self.warmup_calls!r}")

    def describe(self) -> str:
        """Short name for ``BackendInfo.accelerations``, e.g. ``cuda-graph-32-ladder``."""
        return f"cuda-graph-{self.max_keyframes}" + ("-ladder" if self.ladder else "")


@dataclass
class GraphReport:
    """What the runner did: graphs captured (capacity in keyframes -> seconds), replays, eager
    calls and why (``errors``, most recent last, at most 20 kept)."""

    options: GraphOptions
    captures: dict[str, float] = field(default_factory=dict)
    replays: int = 0
    eager: int = 0
    cache_loads: int = 0
    errors: list[str] = field(default_factory=list)


def capacity_ladder(keyframes: int, options: GraphOptions) -> int | None:
    """Keyframe capacity of the graph that serves a map of ``keyframes`` (None: too large)."""
    if keyframes > options.max_keyframes:
        return None
    if not options.ladder:
        return options.max_keyframes
    rung = 1
    while rung < keyframes:
        rung *= 2
    return min(rung, options.max_keyframes)


class StaticCache:
    """K/V buffers of fixed capacity: what a captured step reads (``CacheBuffers`` + ``key_mask``).

    ``capacity`` keyframe tokens, then ``scratch`` tokens for the query frames; it presents its
    whole capacity as "cached" (``length``), so a tracking pass writes its own K/V at the fixed
    offset ``capacity`` and attends over every slot, and ``key_mask(layer)`` (bool
    [capacity + scratch], True = may attend) hides the slots past the loaded map's tokens.
    ``view(capacity)`` is the same storage seen with a smaller capacity (its own mask): the
    graphs of a capacity ladder share one set of buffers.
    """

    def __init__(
        self,
        layout: CacheLayout,
        capacity: int,
        scratch: int,
        *,
        dtype: torch.dtype,
        device: torch.device,
        storage: tuple[list[torch.Tensor], list[torch.Tensor]] | None = None,
    ) -> None:
        self.layout = layout
        self.capacity, self.scratch = int(capacity), int(scratch)
        shape = (1, layout.num_heads, self.capacity + self.scratch, layout.head_dim)
        if storage is None:
            # zeros, not empty: a masked slot's garbage must stay finite (NaN * 0 is NaN)
            keys = [torch.zeros(shape, dtype=dtype, device=device) for _ in range(layout.num_layers)]
            values = [torch.zeros(shape, dtype=dtype, device=device) for _ in range(layout.num_layers)]
            storage = (keys, values)
        self._keys = [k[:, :, : shape[2]] for k in storage[0]]
        self._values = [v[:, :, : shape[2]] for v in storage[1]]
        self._storage = storage
        self._mask = torch.zeros(layout.num_layers, shape[2], dtype=torch.bool, device=device)
        self.lengths: tuple[int, ...] = (0,) * layout.num_layers

    # ---------------------------------------------------------------- CacheBuffers
    @property
    def length(self) -> int:
        return self.capacity

    def layer_length(self, layer: int) -> int:
        return self.capacity

    def ensure_capacity(self, tokens: int) -> None:
        if tokens > self.capacity + self.scratch:
            raise CacheError(
                f"a static cache holds {self.capacity} + {self.scratch} tokens, not {tokens}"
            )

    def buffers(self, layer: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self._keys[layer], self._values[layer]

    def key_mask(self, layer: int) -> torch.Tensor | None:
        """bool [capacity + scratch]: the loaded map's tokens and the scratch (True); None when
        the map fills the capacity (the unmasked step: PyTorch's flash kernel takes no mask)."""
        return None if self.full else self._mask[layer]

    @property
    def full(self) -> bool:
        """Every layer holds ``capacity`` tokens: no slot needs masking."""
        return all(length == self.capacity for length in self.lengths)

    # ---------------------------------------------------------------- loading
    def view(self, capacity: int) -> StaticCache:
        """The same storage with a smaller ``capacity`` (and its own key mask)."""
        if capacity > self.capacity:
            raise CacheError(f"a view of {capacity} tokens exceeds the capacity {self.capacity}")
        device = self._mask.device
        return StaticCache(self.layout, capacity, self.scratch, dtype=self._keys[0].dtype,
                           device=device, storage=self._storage)  # fmt: skip

    def load(self, cache: Any) -> None:
        """Copy every layer's cached tokens of ``cache`` (a ``KVCache``; dequantised if stored
        quantised) to the start of the buffers and set the mask."""
        lengths = tuple(cache.layer_length(i) for i in range(self.layout.num_layers))
        if max(lengths, default=0) > self.capacity:
            raise CacheError(f"a cache of {max(lengths)} tokens exceeds the capacity {self.capacity}")
        for layer, length in enumerate(lengths):
            self._keys[layer][:, :, :length].copy_(cache.keys(layer))
            self._values[layer][:, :, :length].copy_(cache.values(layer))
        self.set_lengths(lengths)

    def set_lengths(self, lengths: tuple[int, ...]) -> None:
        """Mask in the first ``lengths[layer]`` tokens of each layer and the scratch (in place:
        captured graphs read this tensor)."""
        slots = torch.arange(self.capacity + self.scratch, device=self._mask.device)
        held = torch.tensor(lengths, device=self._mask.device).unsqueeze(1)
        self._mask.copy_((slots < held) | (slots >= self.capacity))
        self.lengths = tuple(lengths)


@dataclass
class _Captured:
    replay: Callable[[], Any]  # CUDAGraph.replay
    frames: torch.Tensor  # the static input
    output: Any  # the model output whose tensors the graph writes
    cache: StaticCache  # the view it reads


class GraphTracking:
    """``model.forward_track`` replayed from CUDA graphs (same signature; outputs are copies).

    ``eager`` is the model's own ``forward_track``; ``finish`` (the model's
    ``finish_captured_track`` when it has one) turns a replayed output into the eager one (Pi3:
    the camera head's SVD runs outside the graph).
    """

    def __init__(self, model: nn.Module, layout: CacheLayout, options: GraphOptions) -> None:
        self._eager: Callable[..., Any] = cast(Any, model).forward_track
        self._finish: Callable[[Any], Any] | None = getattr(model, "finish_captured_track", None)
        self._layout, self.options = layout, options
        self._dtype: torch.dtype = model.compute_dtype  # type: ignore[assignment]
        self._device = next(model.parameters()).device
        self.report = GraphReport(options)
        self._lock = threading.Lock()
        self._static: StaticCache | None = None  # the largest capacity; views share its storage
        self._views: dict[int, StaticCache] = {}
        self._graphs: dict[tuple[Any, ...], _Captured] = {}
        self._loaded: tuple[Any, ...] | None = None  # (weakref to the cache, its signature)
        self._pool: Any = None

    def __call__(self, imgs: torch.Tensor, cache: Any, **kwargs: Any) -> Any:
        if self._broken:
            return self._run_eager(None, imgs, cache, kwargs)
        reason = self._ineligible(imgs, cache)
        if reason is not None:
            return self._run_eager(reason, imgs, cache, kwargs)
        # the eager step's own check, before the cache is read: a wrong cache is the caller's
        # CacheError, not a reason to give up on graphs
        self._layout.check_cache(cache, dtype=self._dtype, device=self._device)
        with self._lock:
            capacity = capacity_ladder(cache.num_keyframes, self.options)
            assert capacity is not None  # _ineligible checked it
            tokens = cache.tokens_per_frame
            try:
                self._load(cache, tokens, imgs.dtype)
                full = self._view(capacity * tokens).full  # a full map: its own, unmasked graph
                key = (capacity, full, tuple(imgs.shape), imgs.dtype, tuple(sorted(kwargs.items())))
                captured = self._graphs.get(key)
                if captured is None:
                    captured = self._capture(key, capacity * tokens, imgs, kwargs)
                    twin = (key[0], not full, *key[2:])  # the map filling up: no capture then
                    self._capture(twin, capacity * tokens, imgs, kwargs)
                captured.frames.copy_(imgs)
                captured.replay()
                output = _copy_output(captured.output)
                self._write_back_scratch(captured.cache, cache, imgs.shape[0] * tokens)
            except (RuntimeError, CacheError) as exc:  # a capture CUDA refused: eager from now on
                self._remember(f"graph failed: {type(exc).__name__}: {exc}")
                self._graphs.clear()
                self._broken = True
                return self._run_eager(None, imgs, cache, kwargs)
            self.report.replays += 1
        return output if self._finish is None else self._finish(output)

    # ---------------------------------------------------------------- internals
    _broken = False

    def _ineligible(self, imgs: torch.Tensor, cache: Any) -> str | None:
        if not self._supports(imgs.device):
            return f"device {imgs.device.type} (graphs are CUDA only)"
        if imgs.shape[0] != 1:
            return f"{imgs.shape[0]} query frames (graphs hold one)"
        if not hasattr(cache, "num_keyframes") or not hasattr(cache, "keys"):
            return f"a {type(cache).__name__} is not a KVCache"
        if capacity_ladder(cache.num_keyframes, self.options) is None:
            return f"{cache.num_keyframes} keyframes > max_keyframes {self.options.max_keyframes}"
        return None

    def _run_eager(self, reason: str | None, imgs: torch.Tensor, cache: Any, kwargs: Any) -> Any:
        self.report.eager += 1
        if reason is not None:
            self._remember(reason)
        return self._eager(imgs, cache, **kwargs)

    def _remember(self, reason: str) -> None:
        if not self.report.errors or self.report.errors[-1] != reason:
            self.report.errors = [*self.report.errors[-19:], reason]
            _log.info("tracking step runs eager", reason=reason)

    def _load(self, cache: Any, tokens: int, frames_dtype: torch.dtype) -> None:
        """Copy ``cache`` into the static buffers unless it is the map already loaded."""
        lengths = tuple(cache.layer_length(i) for i in range(self._layout.num_layers))
        signature = (tuple(cache.keyframe_ids), lengths, tokens, cache.dtype)
        if self._loaded is not None:
            reference, loaded_signature = self._loaded
            if reference() is cache and loaded_signature == signature:
                return
        if self._static is None or self._static.scratch != tokens or (
            self._static._keys[0].dtype != cache.dtype
        ):
            self._static = StaticCache(
                self._layout, self.options.max_keyframes * tokens, tokens,
                dtype=cache.dtype, device=cache.device,
            )  # fmt: skip
            self._views, self._graphs = {}, {}
        self._static.load(cache)
        for view in self._views.values():
            view.set_lengths(lengths)
        self._loaded = (weakref.ref(cache), signature)
        self.report.cache_loads += 1

    def _view(self, capacity_tokens: int) -> StaticCache:
        assert self._static is not None
        if capacity_tokens == self._static.capacity:
            return self._static
        if capacity_tokens not in self._views:
            view = self._static.view(capacity_tokens)
            view.set_lengths(self._static.lengths)
            self._views[capacity_tokens] = view
        return self._views[capacity_tokens]

    def _capture(
        self, key: tuple[Any, ...], capacity_tokens: int, imgs: torch.Tensor, kwargs: dict[str, Any]
    ) -> _Captured:
        """The graph of ``key`` (capacity, full, ...): with ``full`` the step is captured
        without the key mask, whatever the loaded map (the mask's content is read at replay,
        only whether there is one is fixed at capture)."""
        start = time.perf_counter()
        view = self._view(capacity_tokens)
        frames = imgs.clone()
        loaded = view.lengths
        view.lengths = (capacity_tokens,) * len(loaded) if key[1] else (0,) * len(loaded)
        try:
            replay, output = self._record(
                lambda: self._eager(frames, view, **kwargs), imgs.device
            )
        finally:
            view.lengths = loaded
        captured = _Captured(replay, frames, output, view)
        self._graphs[key] = captured
        seconds = time.perf_counter() - start
        masked = "full" if key[1] else "masked"
        self.report.captures[f"{key[0]} keyframes {masked}, {key[4]}"] = seconds
        _log.info("tracking step captured", capacity_tokens=capacity_tokens,
                  seconds=round(seconds, 3))  # fmt: skip
        return captured

    def _supports(self, device: torch.device) -> bool:
        return device.type == "cuda"

    def _record(self, step: Callable[[], Any], device: torch.device) -> tuple[Callable[[], Any], Any]:
        """Capture ``step`` in a CUDA graph -> (replay, the output tensors it writes)."""
        side = torch.cuda.Stream(device=device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):  # warm-up off the capturing stream, as PyTorch requires
            for _ in range(self.options.warmup_calls):
                step()
        torch.cuda.current_stream(device).wait_stream(side)
        if self._pool is None:
            self._pool = torch.cuda.graph_pool_handle()
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, pool=self._pool):
            output = step()
        return graph.replay, output

    @staticmethod
    def _write_back_scratch(view: StaticCache, cache: Any, own: int) -> None:
        """The query's K/V into ``cache``'s scratch, where the eager step leaves them."""
        if getattr(cache, "quantized", False):
            return  # a quantised cache's scratch is a shared work pair: nothing to adopt
        cache.ensure_capacity(cache.length + own)
        for layer in range(view.layout.num_layers):
            keys, values = cache.buffers(layer)
            past = cache.layer_length(layer)
            static_keys, static_values = view.buffers(layer)
            keys[:, :, past : past + own].copy_(static_keys[:, :, view.capacity : view.capacity + own])
            values[:, :, past : past + own].copy_(
                static_values[:, :, view.capacity : view.capacity + own]
            )


def _copy_output(output: Any) -> Any:
    """A dataclass of tensors (or None) with every tensor cloned: the next replay overwrites the
    graph's own."""
    if dataclasses.is_dataclass(output) and not isinstance(output, type):
        changes = {
            f.name: _copy_output(getattr(output, f.name)) for f in dataclasses.fields(output)
        }
        return dataclasses.replace(output, **changes)
    if isinstance(output, torch.Tensor):
        return output.clone()
    if isinstance(output, (list, tuple)):
        return type(output)(_copy_output(item) for item in output)
    return output

