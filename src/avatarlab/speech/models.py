"""The two speech animation models.

Seed 000 (`AudioToVisemes`): per video frame a 250 ms window of 65 audio features -> a convolutional encoder with batch
norm -> an LSTM over frames -> two heads: viseme weights a (softmax: on the simplex) and phoneme probabilities p.
The landmarks are a fixed linear layer of the weights: l = Pr(B0) + sum_j a_j (Pr(B_j) - Pr(B0)).
Seed 001 (`PhonemeWindowMLP`, Taylor et al. 2017): the phoneme labels of k_x = 11 frames as the paper's linguistic
indicator vector (`speech/linguistic.py`; `inputs="one_hot"`: the phoneme identities alone) -> 3 tanh layers (3000
wide at paper scale) with dropout 0.5 -> k_y = 5 frames of the reference face's parameters; overlapping predictions
of a frame are averaged.
"""
from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from avatarlab.runtime.safe_load import load_tensors


class AudioToVisemes(nn.Module):
    def __init__(self, n_features: int, n_visemes: int, n_phonemes: int, basis: torch.Tensor, channels: int = 64,
                 hidden: int = 128, phoneme_head: bool = True):
        super().__init__()
        self.encoder = nn.Sequential(
            nn.Conv1d(n_features, channels, 3, padding=1), nn.BatchNorm1d(channels), nn.ReLU(),
            nn.Conv1d(channels, channels, 3, stride=2, padding=1), nn.BatchNorm1d(channels), nn.ReLU(),
            nn.Conv1d(channels, channels, 3, stride=2, padding=1), nn.BatchNorm1d(channels), nn.ReLU(),
            nn.AdaptiveAvgPool1d(1))
        self.lstm = nn.LSTM(channels, hidden, batch_first=True)
        self.visemes = nn.Linear(hidden, n_visemes)
        # seed 000 without its regulariser has no phoneme module: then the logits are None
        self.phonemes = nn.Linear(hidden, n_phonemes) if phoneme_head else None
        self.register_buffer("basis", basis.reshape(basis.shape[0], -1))  # (n_visemes, 136): Pr(B_j), row 0 = B0
        self.register_buffer("mean", torch.zeros(n_features))
        self.register_buffer("std", torch.ones(n_features))

    def forward(self, windows: torch.Tensor, state=None):
        """windows (B, T, W, F) -> viseme weights (B, T, K), phoneme logits (B, T, P) or None (no phoneme module),
        landmarks (B, T, 68, 2), LSTM state."""
        b, t, w, f = windows.shape
        x = ((windows - self.mean) / self.std).reshape(b * t, w, f).transpose(1, 2)
        h = self.encoder(x).reshape(b, t, -1)
        h, state = self.lstm(h, state)
        weights = torch.softmax(self.visemes(h), -1)
        logits = self.phonemes(h) if self.phonemes is not None else None
        return weights, logits, self.landmarks(weights), state

    def landmarks(self, weights: torch.Tensor) -> torch.Tensor:
        b0 = self.basis[0]
        flat = b0 + weights @ (self.basis - b0)
        return flat.reshape(*weights.shape[:-1], 68, 2)


def phoneme_regularizer(weights: torch.Tensor, logits: torch.Tensor, phoneme_to_viseme: torch.Tensor) -> torch.Tensor:
    """Seed 000's regulariser (1/T) sum_t sum_k a_tk (1 - p_tk), with p_tk = P(viseme k) summed from the phoneme
    probabilities: a viseme weight costs what the phoneme head finds it unlikely."""
    p_vis = torch.softmax(logits, -1) @ phoneme_to_viseme
    return (weights * (1 - p_vis)).sum(-1).mean()


def speech_loss(weights, logits, landmarks, target_landmarks, target_phonemes, phoneme_to_viseme, lambda1, lambda2):
    """L = L_land + lambda1 CE(phonemes) + lambda2 (1/T) sum_t sum_k a_tk (1 - p_tk), p_tk = P(viseme k) from the
    phoneme probabilities: the weights may only use visemes the phoneme head finds likely (seed 000's regulariser)."""
    land = ((landmarks - target_landmarks) ** 2).sum(-1).mean()
    if logits is None:  # no phoneme module: the landmark term alone
        return land, {"landmarks": float(land.detach()), "ce": 0.0, "reg": 0.0}
    ce = nn.functional.cross_entropy(logits.reshape(-1, logits.shape[-1]), target_phonemes.reshape(-1))
    reg = phoneme_regularizer(weights, logits, phoneme_to_viseme)
    total = land + lambda1 * ce + lambda2 * reg
    return total, {"landmarks": float(land.detach()), "ce": float(ce.detach()), "reg": float(reg.detach())}


class PhonemeWindowMLP(nn.Module):
    INPUTS = ("linguistic", "one_hot")

    def __init__(self, n_phonemes: int, n_outputs: int, k_x: int = 11, k_y: int = 5, hidden: int = 3000,
                 layers: int = 3, dropout: float = 0.5, inputs: str = "one_hot"):
        super().__init__()
        from avatarlab.speech.linguistic import category_matrix, coarse_class, linguistic_size
        from avatarlab.speech.visemes import PHONEMES

        if inputs not in self.INPUTS:
            raise ValueError(f"speech.window_inputs must be one of {self.INPUTS}, got {inputs!r}")
        if inputs == "linguistic" and n_phonemes != len(PHONEMES):
            raise ValueError(f"linguistic inputs describe the {len(PHONEMES)} phonemes of visemes.PHONEMES, "
                             f"not {n_phonemes}")
        self.k_x, self.k_y, self.n_outputs, self.inputs = k_x, k_y, n_outputs, inputs
        linguistic = inputs == "linguistic"
        self.register_buffer("categories", category_matrix() if linguistic else torch.zeros(0), persistent=False)
        self.register_buffer("classes", coarse_class() if linguistic else torch.zeros(0, dtype=torch.long),
                             persistent=False)
        dims = [linguistic_size(k_x) if linguistic else k_x * n_phonemes] + [hidden] * layers
        blocks = []
        for a, b in zip(dims[:-1], dims[1:]):
            blocks += [nn.Linear(a, b), nn.Tanh(), nn.Dropout(dropout)]
        self.net = nn.Sequential(*blocks, nn.Linear(dims[-1], k_y * n_outputs))
        self.n_phonemes = n_phonemes

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        """(B, k_x, P) one-hot or (B, D) linguistic windows -> (B, k_y, D)."""
        return self.net(windows.flatten(1)).reshape(-1, self.k_y, self.n_outputs)

    def windows(self, labels: torch.Tensor) -> torch.Tensor:
        """(T,) phoneme ids -> the model's input for the windows centred on every frame (edges padded with
        silence): (T, k_x, P) one-hot, or (T, D) linguistic indicators."""
        from avatarlab.speech.linguistic import linguistic_features

        half = self.k_x // 2
        silence = torch.zeros(half, dtype=labels.dtype, device=labels.device)
        padded = torch.cat([silence, labels, silence])
        idx = torch.arange(len(labels), device=labels.device)[:, None] + torch.arange(self.k_x, device=labels.device)[None]
        if self.inputs == "linguistic":
            return linguistic_features(padded[idx], self.categories, self.classes)
        return nn.functional.one_hot(padded[idx], self.n_phonemes).float()

    @torch.no_grad()
    def predict_sequence(self, labels: torch.Tensor) -> torch.Tensor:
        """(T,) -> (T, D) on the CPU: every frame's prediction averaged over the k_y outputs that cover it."""
        labels = labels.to(self.net[0].weight.device)
        out = self(self.windows(labels)).cpu()  # (T, k_y, D): output j of window t is frame t - k_y//2 + j
        total = torch.zeros(len(labels), self.n_outputs)
        count = torch.zeros(len(labels), 1)
        for j in range(self.k_y):
            frames = torch.arange(len(labels)) - self.k_y // 2 + j
            ok = (frames >= 0) & (frames < len(labels))
            total.index_add_(0, frames[ok], out[ok, j])
            count.index_add_(0, frames[ok], torch.ones(int(ok.sum()), 1))
        return total / count.clamp(min=1)


def load_speech_model(path: str | Path, head, device: torch.device | str = "cpu") -> "AudioToVisemes":
    """The seed-000 model saved by the speech training step (weights only)."""
    from avatarlab.speech.visemes import NAMES, PHONEMES, viseme_basis

    state = load_tensors(path, "a speech model (model.pt)")
    if not isinstance(state, dict) or state.get("kind") != "lstm":
        raise ValueError(f"{path}: audio animation needs the seed-000 (lstm) model, this is {state.get('kind')!r}")
    model = AudioToVisemes(state["n_features"], len(NAMES), len(PHONEMES), viseme_basis(head), state["channels"],
                           state["hidden"], bool(state.get("phoneme_head", True)))
    model.load_state_dict(state["model"])
    return model.eval().to(device)
