"""Training batches: each sample is synthetic with probability p(n) (eq. 9) and real otherwise (seed 002, 3.3).

A synthetic sample is a head-model render of a real image's fit with noise (data/synthetic.py), from the
mouth-interior head during alpha2's last phase; a real sample is a frame of the real set with its fit, its index (for
the learnable offsets of eq. 8) and, when the recipe says so, the z-distance augmentation. Every random choice comes
from one CPU generator, so a run draws the same batches on any device and after a resume.
`BatchStream` draws the next batch in a background thread while the current one trains (the renders are many small
operations that leave the second core idle); the generator state before the next unconsumed batch is what a
checkpoint stores.
"""
from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import torch

from avatarlab.data.real_images import RealImageSet, z_augment
from avatarlab.data.schedule import Schedule
from avatarlab.data.synthetic import SyntheticGenerator
from avatarlab.render.camera import Camera

GEOMETRY_KEYS = ("shape", "expression", "pose", "texture")


@dataclass
class Batch:
    images: torch.Tensor  # (B, 3, S, S) in [0, 1]
    masks: torch.Tensor  # (B, 1, S, S)
    params: dict  # shape, expression, pose (B, 15), texture
    lighting: torch.Tensor  # (B, 9, 3)
    camera: Camera
    real_index: torch.Tensor  # (B,) index into the real set, -1 for a synthetic sample
    p_synthetic: float

    @property
    def n_synthetic(self) -> int:
        return int((self.real_index < 0).sum())


@dataclass
class BatchSource:
    """What a batch is drawn from. `mouth_from`: the iteration from which synthetic samples come from
    `synthetic_mouth` (alpha2)."""

    synthetic: SyntheticGenerator | None
    real: RealImageSet
    schedule: Schedule
    batch_size: int
    device: torch.device
    z_aug: bool = False
    z_aug_range: tuple[float, float] = (0.8, 1.2)
    z_aug_p: float = 0.5
    synthetic_mouth: SyntheticGenerator | None = None

    @torch.no_grad()
    def draw(self, iteration: int, g: torch.Generator) -> Batch:
        """The batch of `iteration` (1-based)."""
        p = self.schedule.probability(iteration)
        b = self.batch_size
        if self.synthetic is None or p <= 0:
            n_syn = 0
        elif p >= 1:
            n_syn = b
        else:
            n_syn = int(torch.binomial(torch.tensor(float(b)), torch.tensor(p), generator=g))
        parts = []
        if n_syn:
            mouth = self.schedule.mouth_from is not None and iteration > self.schedule.mouth_from
            gen = self.synthetic_mouth if mouth and self.synthetic_mouth is not None else self.synthetic
            s = gen.sample(n_syn, g)
            parts.append((s["images"], s["masks"], s["params"], s["lighting"], s["camera"],
                          torch.full((n_syn,), -1, dtype=torch.long)))
        if b - n_syn:
            idx = torch.randint(0, len(self.real), (b - n_syn,), generator=g)
            images, masks, camera = self.real.images[idx], self.real.masks[idx], self.real.camera(idx)
            if self.z_aug:
                images, masks, camera = z_augment(images, masks, camera, g, *self.z_aug_range, p=self.z_aug_p)
            params = self.real.select(idx)
            parts.append((images.to(self.device), masks.to(self.device),
                          {k: params[k].to(self.device) for k in GEOMETRY_KEYS},
                          params["lighting"].to(self.device), camera.to(self.device), idx))
        return Batch(images=torch.cat([p[0] for p in parts]), masks=torch.cat([p[1] for p in parts]),
                     params={k: torch.cat([p[2][k] for p in parts]) for k in GEOMETRY_KEYS},
                     lighting=torch.cat([p[3] for p in parts]), camera=Camera.cat([p[4] for p in parts]),
                     real_index=torch.cat([p[5] for p in parts]).to(self.device), p_synthetic=p)


class BatchStream:
    """The batches of iterations start+1 .. last, in order, each drawn one ahead in a background thread."""

    def __init__(self, source: BatchSource, start: int, last: int, g: torch.Generator):
        self.source, self.next_iteration, self.last, self.g = source, start + 1, last, g
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="batches")
        self.pending = self._submit(self.next_iteration)

    def _submit(self, iteration: int):
        if iteration > self.last:
            return None

        def work():
            state = self.g.get_state()
            return state, self.source.draw(iteration, self.g)

        return self.pool.submit(work)

    def next(self) -> Batch:
        _, batch = self.pending.result()
        self.next_iteration += 1
        self.pending = self._submit(self.next_iteration)
        return batch

    def resume_state(self) -> torch.Tensor:
        """The generator state from which the next unconsumed batch is drawn (what a checkpoint keeps)."""
        if self.pending is None:
            return self.g.get_state()
        state, _ = self.pending.result()
        return state

    def close(self):
        self.pool.shutdown(wait=True, cancel_futures=True)
