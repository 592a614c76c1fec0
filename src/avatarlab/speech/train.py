"""Train and evaluate a speech animation model on the corpus (seed 000 with / without its regulariser, seed 001).

Landmarks of every frame are first aligned to the neutral viseme shape Pr(B0) by a similarity Procrustes fit
(Kabsch rotation + scale + shift) on the stable points (brows, nose, eyes), as seed 000 aligns video landmarks.
Seed 001's output is retargeted to the head model's rig (jaw + expression) through +-3 sigma reference poses of the
first four components, w_k^u = max(p_k / (3 u sigma_k), 0) on the (whitened) component values.
Metric (seed 000): lip-landmark error normalised by the outer-eye distance ||l37 - l46|| (1-based), in percent,
on the test speakers; latency = the look-ahead + compute per step; real-time factor = compute / audio time.
`python -m avatarlab.speech.train speech.model=lstm speech.regularize=true speech.out_dir=...`
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from avatarlab.headmodel import load_head_model
from avatarlab.runtime.config import CPU, autocast, grad_scaler
from avatarlab.runtime.entry import entry_point
from avatarlab.runtime.io import atomic_path, write_json
from avatarlab.runtime.tracking import start_run
from avatarlab.speech.augment import augment, check_settings
from avatarlab.speech.features import FeatureSpec, windows
from avatarlab.speech.lip_metrics import align_to, baseline_scores, lip_error_percent, motion_only
from avatarlab.speech.models import AudioToVisemes, PhonemeWindowMLP, speech_loss
from avatarlab.speech.visemes import NAMES, PHONEMES, frontal_landmarks, phoneme_to_viseme_matrix, viseme_basis

log = logging.getLogger(__name__)
READS = ('seed', 'amp', 'head_model', 'speech', 'tracking')  # the config sections this step reads (runtime/entry.py)



class Corpus:
    """The corpus's utterances as model inputs; each training utterance also `copies` times augmented (`augment`:
    channel, reverberation, noise, gain drawn from `augmentation`, conf `speech.augment`), same labels and
    landmarks: training audio closer to a real recording's."""

    def __init__(self, path: Path, basis: np.ndarray, spec: FeatureSpec, augmentation=None, copies: int = 0,
                 seed: int = 0):
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no speech corpus (rule speech_corpus)")
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
        self.labels = data["labels"]
        self.landmarks = align_to(data["landmarks"], basis[0])
        self.items = []
        rng = np.random.default_rng(seed)
        rate = int(data["sample_rate"])
        for k in range(len(data["item_split"])):
            a0, an = int(data["item_audio_start"][k]), int(data["item_audio_len"][k])
            f0, fn = int(data["item_frame_start"][k]), int(data["item_frames"][k])
            split, clean = str(data["item_split"][k]), data["audio"][a0:a0 + an]
            versions = [clean] + [augment(clean, rate, rng, augmentation) for _ in range(copies if split == "train"
                                                                                       else 0)]
            for number, audio in enumerate(versions):
                self.items.append({"split": split, "speaker": int(data["item_speaker"][k]), "augmented": number > 0,
                                   "windows": windows(audio, rate, fn, spec),
                                   "labels": self.labels[f0:f0 + fn], "landmarks": self.landmarks[f0:f0 + fn],
                                   "seconds": an / rate})

    def split(self, name: str) -> list[dict]:
        return [i for i in self.items if i["split"] == name]


def train_lstm(cfg, corpus: Corpus, basis: torch.Tensor, regularize: bool, device=CPU):
    """Seed 000's model trained on `device`, with mixed precision if `cfg.amp` (the loss in float32).
    The landmark targets are each speaker's motion on the neutral face Pr(B0) (the frame minus its utterance's mean
    shape, plus Pr(B0)): the model's landmarks are Pr(B0) plus viseme offsets and cannot carry a speaker's face, so
    the identity part of the raw error would only pull the viseme weights away from the mouth's motion."""
    sp = cfg.speech
    train_items = corpus.split("train")
    neutral = basis[0].numpy()
    targets = [item["landmarks"] - item["landmarks"].mean(0, keepdims=True) + neutral for item in train_items]
    feats = np.concatenate([i["windows"].reshape(-1, i["windows"].shape[-1]) for i in train_items])
    model = AudioToVisemes(feats.shape[1], len(NAMES), len(PHONEMES), basis, int(cfg.speech.channels),
                           int(cfg.speech.hidden), phoneme_head=bool(sp.phoneme_head))
    model.mean.copy_(torch.from_numpy(feats.mean(0)))
    model.std.copy_(torch.from_numpy(feats.std(0) + 1e-5))
    model.to(device)
    optim = torch.optim.Adam(model.parameters(), lr=float(sp.lr), weight_decay=float(sp.weight_decay))
    plateau = torch.optim.lr_scheduler.ReduceLROnPlateau(optim, factor=0.5, patience=5)
    amp = bool(cfg.get("amp", False))
    scaler = grad_scaler(device, amp)
    m = phoneme_to_viseme_matrix().to(device)
    rng = np.random.default_rng(int(cfg.seed))
    chunk, batch = int(sp.chunk_frames), int(sp.batch)
    lambda2 = float(sp.lambda2) if regularize else 0.0
    history = []
    for epoch in range(int(cfg.speech.epochs)):
        model.train()
        order = rng.permutation(len(train_items))
        for start in range(0, len(order), batch):
            xs, ys, ps = [], [], []
            for k in order[start:start + batch]:
                item = train_items[k]
                n = len(item["labels"])
                s = int(rng.integers(0, max(1, n - chunk + 1)))
                sl = slice(s, min(n, s + chunk))
                pad = chunk - (sl.stop - sl.start)
                w, lab, lm = item["windows"][sl], item["labels"][sl], targets[k][sl]
                if pad:
                    w = np.concatenate([w, np.repeat(w[-1:], pad, 0)])
                    lab = np.concatenate([lab, np.repeat(lab[-1:], pad)])
                    lm = np.concatenate([lm, np.repeat(lm[-1:], pad, 0)])
                xs.append(w), ys.append(lm), ps.append(lab)
            x = torch.from_numpy(np.stack(xs)).to(device)
            with autocast(device, amp):
                outputs = model(x)
            weights, logits, landmarks = (o.float() if o is not None else None for o in outputs[:3])
            loss, parts = speech_loss(weights, logits, landmarks, torch.from_numpy(np.stack(ys)).to(device),
                                      torch.from_numpy(np.stack(ps)).to(device), m, float(sp.lambda1), lambda2)
            optim.zero_grad()
            scaler.scale(loss).backward()
            scaler.step(optim)
            scaler.update()
        val = evaluate_lstm(model, corpus.split("val"))
        plateau.step(val["motion_lip_error_percent"])
        history.append({"epoch": epoch + 1, "loss": float(loss), **parts, "val_lip_error_percent":
                        val["lip_error_percent"], "val_motion_lip_error_percent": val["motion_lip_error_percent"]})
        log.info("epoch %d loss %.5f val lip error %.2f %% IOD (motion %.2f %%)", epoch + 1, float(loss),
                 val["lip_error_percent"], val["motion_lip_error_percent"])
    return model, history


@torch.no_grad()
def evaluate_lstm(model: AudioToVisemes, items: list[dict]) -> dict:
    model.eval()
    device = model.mean.device
    preds, truths, correct, total = [], [], 0, 0
    for item in items:
        _, logits, landmarks, _ = model(torch.from_numpy(item["windows"])[None].to(device))
        preds.append(landmarks[0].cpu().numpy())
        truths.append(item["landmarks"])
        if logits is not None:
            correct += int((logits[0].cpu().argmax(-1).numpy() == item["labels"]).sum())
        total += len(item["labels"])
    return {**lip_errors(preds, truths),
            "phoneme_accuracy": correct / max(total, 1) if model.phonemes is not None else None}


def lip_errors(preds: list[np.ndarray], truths: list[np.ndarray]) -> dict:
    """Per-utterance predictions and truths -> the raw lip error and the error of the mouth's motion alone."""
    truth = np.concatenate(truths)
    return {"lip_error_percent": lip_error_percent(np.concatenate(preds), truth),
            "motion_lip_error_percent": lip_error_percent(motion_only(preds, truths), truth)}


@torch.no_grad()
def streaming_cost(model: AudioToVisemes, item: dict) -> float:
    """Seconds of compute per step when frames arrive one by one (LSTM state carried over)."""
    model.eval()
    device = model.mean.device
    state, x = None, torch.from_numpy(item["windows"])[None].to(device)
    start = time.perf_counter()
    for t in range(x.shape[1]):
        *_, state = model(x[:, t:t + 1], state)
        if device.type == "cuda":
            torch.cuda.synchronize(device)  # each frame's output is needed before the next arrives
    return (time.perf_counter() - start) / x.shape[1]


def train_window(cfg, corpus: Corpus, device=CPU):
    """Seed 001's model trained on `device`, with mixed precision if `cfg.amp`."""
    sp = cfg.speech
    train_items = corpus.split("train")
    flat = np.concatenate([i["landmarks"].reshape(len(i["landmarks"]), -1) for i in train_items])
    mean = flat.mean(0)  # the mean face; the components describe the motion within an utterance (each utterance's
    motion = [(i["landmarks"] - i["landmarks"].mean(0, keepdims=True)).reshape(len(i["landmarks"]), -1)
              for i in train_items]  # own mean removed): the reference face of seed 001 is one face that moves
    _, sv, vt = np.linalg.svd(np.concatenate(motion), full_matrices=False)
    n_pca = int(cfg.speech.pca)
    comps, sigma = vt[:n_pca], sv[:n_pca] / np.sqrt(len(flat) - 1)
    model = PhonemeWindowMLP(len(PHONEMES), n_pca, int(sp.k_x), int(sp.k_y), int(cfg.speech.window_hidden),
                             inputs=str(sp.window_inputs))
    model.to(device)
    optim = torch.optim.Adam(model.parameters(), lr=float(sp.lr))
    amp = bool(cfg.get("amp", False))
    scaler = grad_scaler(device, amp)
    xs, ys = [], []
    half = model.k_y // 2
    for item, moves in zip(train_items, motion):
        labels = torch.from_numpy(item["labels"])
        coef = moves @ comps.T / sigma  # whitened targets
        padded = np.concatenate([np.repeat(coef[:1], half, 0), coef, np.repeat(coef[-1:], half, 0)])
        xs.append(model.windows(labels))
        ys.append(np.stack([padded[t:t + model.k_y] for t in range(len(labels))]))
    x, y = torch.cat(xs).to(device), torch.from_numpy(np.concatenate(ys)).float().to(device)
    g = torch.Generator().manual_seed(int(cfg.seed))
    history = []
    for epoch in range(int(cfg.speech.epochs)):
        model.train()
        perm = torch.randperm(len(x), generator=g)
        for k in range(0, len(x), int(sp.window_batch)):
            idx = perm[k:k + int(sp.window_batch)]
            with autocast(device, amp):
                pred = model(x[idx])
            loss = ((pred.float() - y[idx]) ** 2).mean()
            optim.zero_grad()
            scaler.scale(loss).backward()
            scaler.step(optim)
            scaler.update()
        history.append({"epoch": epoch + 1, "loss": float(loss)})
    pca = {"mean": mean, "components": comps, "sigma": sigma}
    return model, pca, history


def evaluate_window(model: PhonemeWindowMLP, pca: dict, items: list[dict]) -> dict:
    model.eval()
    preds, truths = [], []
    for item in items:
        coef = model.predict_sequence(torch.from_numpy(item["labels"])).numpy()
        preds.append((pca["mean"] + (coef * pca["sigma"]) @ pca["components"]).reshape(-1, 68, 2))
        truths.append(item["landmarks"])
    return lip_errors(preds, truths)


def rig_jacobian(head, components: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """Frontal landmarks of the neutral head (68, 2) and their change per unit of [jaw, expression 0..n-1]."""
    n = min(components, head.n_expression)
    zero = torch.zeros(1, head.n_shape)
    expr = torch.zeros(n + 2, head.n_expression)
    expr[2:, :n] = torch.eye(n)
    jaw = torch.zeros(n + 2)
    jaw[1] = 0.05  # finite difference: the jaw is a rotation
    with torch.no_grad():
        lms = frontal_landmarks(head, zero, expr, jaw)
    d = (lms[1:] - lms[:1]).reshape(n + 1, -1)
    d[0] /= 0.05
    return lms[0], d.T  # (136, n + 1)


def reference_poses(head, pca: dict, basis0: np.ndarray, n_components: int = 4, ridge: float = 1e-4):
    """Seed 001's retargeting: for the first components k and u = +-1, the head-model pose [jaw, expression] whose
    landmarks best match the reference face's mean + 3 u sigma_k PC_k (least squares on the rig's Jacobian)."""
    neutral, J = rig_jacobian(head)
    poses = np.zeros((n_components, 2, J.shape[1]), np.float32)
    A = J.numpy().astype(np.float64)
    for k in range(n_components):
        for ui, u in enumerate((1.0, -1.0)):
            target = pca["mean"] + 3 * u * pca["sigma"][k] * pca["components"][k]
            delta = target - pca["mean"]  # the component's motion, applied to the head's own neutral face
            poses[k, ui] = np.linalg.solve(A.T @ A + ridge * np.eye(A.shape[1]), A.T @ delta)
    return poses


def retarget(coef: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Rig parameters from whitened component values: sum_k sum_u w_k^u R_k^u, w_k^u = max(p_k / (3 u), 0)."""
    n = poses.shape[0]
    w = np.stack([np.maximum(coef[:, :n] / 3.0, 0), np.maximum(-coef[:, :n] / 3.0, 0)], 2)  # (T, n, 2)
    return np.einsum("tku,kup->tp", w, poses)


def retargeted_landmarks(head, rig: np.ndarray) -> np.ndarray:
    n = rig.shape[1] - 1
    expr = torch.zeros(len(rig), head.n_expression)
    expr[:, :n] = torch.from_numpy(rig[:, 1:]).float()
    with torch.no_grad():
        return frontal_landmarks(head, torch.zeros(1, head.n_shape), expr,
                                 torch.from_numpy(rig[:, 0]).float()).numpy()


@entry_point(READS)
def main(cfg, device) -> None:
    sp = cfg.speech
    head = load_head_model(cfg.head_model)
    basis = viseme_basis(head)
    spec = FeatureSpec(sample_rate=int(sp.sample_rate))
    check_settings(sp.augment)
    copies = int(sp.augment.copies) if sp.model == "lstm" else 0  # seed 001 reads phoneme labels, not audio
    corpus = Corpus(Path(sp.corpus), basis.numpy(), spec, sp.augment, copies, int(cfg.seed))
    out_dir = Path(sp.out_dir)
    name = sp.name
    test = corpus.split("test")
    start = time.perf_counter()
    with start_run(cfg, "speech", name, {"speech_model": name}, output=out_dir) as run:
        mlf = None
        if run is not None:
            import mlflow as mlf
        if sp.model == "lstm":
            model, history = train_lstm(cfg, corpus, basis, bool(sp.regularize), device)
            seconds = time.perf_counter() - start
            metrics = evaluate_lstm(model, test)
            step = streaming_cost(model, test[0])
            metrics.update({"compute_ms_per_step": 1000 * step, "lookahead_ms": spec.lookahead_ms,
                            "latency_ms": spec.lookahead_ms + 1000 * step,
                            "real_time_factor": step * 1000 / spec.hop_ms})
            state = {"model": model.state_dict(), "kind": "lstm", "n_features": int(model.mean.shape[0]),
                     "channels": int(cfg.speech.channels), "hidden": int(cfg.speech.hidden),
                     "phoneme_head": bool(sp.phoneme_head)}
        elif sp.model == "window":
            model, pca, history = train_window(cfg, corpus, device)
            seconds = time.perf_counter() - start
            metrics = evaluate_window(model, pca, test)
            # retarget the predicted reference-face motion onto the head model's rig and measure what survives
            poses = reference_poses(head, pca, basis[0].numpy())
            preds, truths = [], []
            for item in test:
                coef = model.predict_sequence(torch.from_numpy(item["labels"])).numpy()
                moved = retargeted_landmarks(head, retarget(coef, poses))
                # the rig carries the mean head's face, the truth the speaker's: compare motion, not identity
                preds.append(moved + (item["landmarks"] - moved).mean(0, keepdims=True))
                truths.append(item["landmarks"])
            metrics["retargeted_lip_error_percent"] = lip_error_percent(np.concatenate(preds), np.concatenate(truths))
            pca["reference_poses"] = poses
            metrics.update({"lookahead_ms": 1000 * (int(sp.k_x) // 2) / 25.0,
                            "latency_ms": 1000 * (int(sp.k_x) // 2) / 25.0,
                            "input": f"phoneme labels ({sp.window_inputs})", "input_size": model.net[0].in_features})
            state = {"model": model.state_dict(), "kind": "window",  # tensors and plain values: weights_only loads
                     "pca": {k: torch.as_tensor(np.asarray(v)) for k, v in pca.items()}}
        else:
            raise ValueError(f"speech.model={sp.model!r}: expected lstm or window")
        # an audio model is not told the phonemes: the phoneme lookup is a reference for it, not its baseline
        fair = ("still_mouth", "phoneme_mean") if sp.model == "window" else ("still_mouth",)
        metrics.update(baseline_scores(corpus.split("train"), test, metrics["motion_lip_error_percent"], fair))
        log.info("%s: motion lip error %.2f %% IOD vs best trivial predictor %s %.2f %% (gain %+.2f)", name,
                 metrics["motion_lip_error_percent"], metrics["best_baseline"],
                 metrics["baselines"][metrics["best_baseline"]], metrics["gain_over_best_baseline"])
        state["model"] = {k: v.cpu() for k, v in state["model"].items()}  # loadable without the training device
        state["config"] = OmegaConf.to_container(cfg, resolve=True)
        with atomic_path(out_dir / "model.pt") as tmp:
            torch.save(state, tmp)
        report = {"model": name, "train_seconds": seconds, "test": metrics, "history": history,
                  "test_utterances": len(test),
                  "train_utterances": sum(not i["augmented"] for i in corpus.split("train")),
                  "augmented_copies": copies}
        write_json(out_dir / "metrics.json", report)
        if mlf is not None:
            for epoch in history:  # the training curves, one step per epoch
                mlf.log_metrics({f"train_{k}": float(v) for k, v in epoch.items() if k != "epoch"},
                                step=int(epoch["epoch"]))
            mlf.log_metrics({f"test_{k}": v for k, v in metrics.items() if isinstance(v, float)})
            mlf.log_metrics({f"baseline_{k}_lip_error_percent": v for k, v in metrics["baselines"].items()})
            mlf.log_metric("train_seconds", seconds)
    log.info("%s: test lip error %.2f %% IOD, latency %.0f ms (%.0fs training)", name,
             metrics["lip_error_percent"], metrics["latency_ms"], seconds)


if __name__ == "__main__":
    main()
