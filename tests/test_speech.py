"""Speech-driven animation: features, espeak-ng and Festival timings, visemes, the models and their loss, alignment, metric."""
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import REPO, SHARED_DATA

from avatarlab.speech.features import FeatureSpec, frame_features, read_wav, windows, write_wav
from avatarlab.speech.lip_metrics import align_to, lip_error_percent
from avatarlab.speech.models import AudioToVisemes, PhonemeWindowMLP, speech_loss
from avatarlab.speech.visemes import (
    NAMES,
    PHONEMES,
    mouth_features,
    normalise_phoneme,
    phoneme_to_viseme_matrix,
    viseme_basis,
    viseme_of,
)
from avatarlab.workflow.layout import ResultsTree

needs_espeak = pytest.mark.skipif(shutil.which("espeak-ng") is None,
                                  reason="Debian's espeak-ng is not installed (`make test` installs it where it can)")


def test_feature_windows_follow_seed_000():
    rate = 25_000
    t = np.arange(rate * 2) / rate
    audio = 0.3 * np.sin(2 * np.pi * 440 * t) * (t > 1)  # silence, then a tone from 1 s on
    feats = frame_features(audio.astype(np.float32))
    assert feats.shape[1] == 13 + 26 + 26 == 65 and abs(len(feats) - 200) <= 2  # 10 ms steps
    win = windows(audio.astype(np.float32), rate)
    assert win.shape == (50, 25, 65)  # one 250 ms window per 40 ms video frame over 2 s
    energy = win[:, -1, 13:39].mean(1)  # log filterbank of the newest analysis frame of each window
    # the window of frame t ends 130 ms after t * 40 ms: the tone (at 1.0 s) shows from frame 22 on (0.88 + 0.13 s)
    assert energy[23] - energy[20] > 5 and np.argmax(np.diff(energy)) in (21, 22)
    centroids = win[:, -1, 39:]
    assert ((centroids >= 0) & (centroids <= 1)).all()


def test_wav_round_trip_and_bad_file(tmp_path):
    audio = np.sin(np.linspace(0, 100, 8000)).astype(np.float32) * 0.5
    write_wav(tmp_path / "a.wav", audio, 16000)
    back, rate = read_wav(tmp_path / "a.wav")
    assert rate == 16000 and np.abs(back - audio).max() < 1e-4
    (tmp_path / "bad.wav").write_bytes(b"not a wav")
    with pytest.raises(ValueError, match="bad.wav: not a PCM WAV"):
        read_wav(tmp_path / "bad.wav")


@needs_espeak
def test_espeak_gives_phonemes_in_order_with_times():
    from avatarlab.speech.tts import Espeak

    utt = Espeak().synthesize("bin blue at f two now")
    names = [normalise_phoneme(p) for p, _, _ in utt.phonemes]
    assert names[:3] == ["b", "I", "n"] and "aU" in names
    starts = [s for _, s, _ in utt.phonemes]
    assert starts == sorted(starts) and utt.phonemes[-1][2] == pytest.approx(len(utt.audio) / utt.rate, abs=0.02)
    assert [w for w, _ in utt.words] == ["bin", "blue", "at", "f", "two", "now"]


needs_festival = pytest.mark.skipif(
    shutil.which("festival") is None or not Path("/usr/share/festival/voices/us/cmu_us_slt_arctic_hts").is_dir(),
    reason="Debian's festival and festvox voices are not installed (`make test` installs them where it can)")


@needs_festival
@pytest.mark.parametrize("voice", ["festival:kal_diphone", "festival:cmu_us_slt_arctic_hts"])
def test_festival_gives_espeak_phonemes_with_times_that_match_its_audio(voice):
    """Festival's segments, mapped to espeak's phonemes: the same word starts as espeak's, ordered times ending with
    the audio, silence where the segments say pause (the leading pause is far quieter than the speech) and a slower
    voice with a larger duration stretch, and (diphone voices) a higher voice with a larger pitch factor."""
    from avatarlab.speech.festival import Festival

    utt, slow = Festival(voice).synthesize_many(["bin blue at f two now", "bin blue at f two now"])[0], \
        Festival(voice, duration_stretch=1.4).synthesize("bin blue at f two now")
    names = [p for p, _, _ in utt.phonemes]
    assert names[:4] == ["_", "b", "I", "n"] and "aU" in names and all(n in PHONEMES for n in names)
    assert all(s < e for _, s, e in utt.phonemes) and utt.phonemes[-1][2] == pytest.approx(len(utt.audio) / utt.rate,
                                                                                           abs=0.05)
    _, _, pause_end = utt.phonemes[0]
    rms = lambda a: float(np.sqrt(np.mean(a ** 2)))  # noqa: E731
    pause, speech = utt.audio[: int(pause_end * utt.rate * 0.8)], utt.audio[int(pause_end * utt.rate):]
    assert rms(pause) < 0.1 * rms(speech)
    assert len(slow.audio) / slow.rate > 1.2 * len(utt.audio) / utt.rate
    assert slow.phonemes[-1][2] == pytest.approx(len(slow.audio) / slow.rate, abs=0.05)
    if voice.endswith("_diphone"):
        high = Festival(voice, pitch_factor=1.4).synthesize("bin blue at f two now")
        assert median_f0(high.audio, high.rate) > 1.25 * median_f0(utt.audio, utt.rate)


def median_f0(audio: np.ndarray, rate: int) -> float:
    """Median pitch (Hz) over the voiced 40 ms frames, by autocorrelation in 60-400 Hz."""
    n, out = int(0.04 * rate), []
    for start in range(0, len(audio) - n, n):
        x = audio[start:start + n].astype(np.float64)
        if np.sqrt(np.mean(x ** 2)) < 0.02:
            continue
        c = np.correlate(x, x, "full")[n - 1:]
        lo, hi = rate // 400, rate // 60
        out.append(rate / (lo + np.argmax(c[lo:hi])))
    return float(np.median(out))


def test_festival_errors_are_one_line_and_its_text_cannot_leave_the_string():
    from avatarlab.speech.festival import Festival, FestivalError, scheme_string

    assert scheme_string('a "quoted" \\ word)\n(system "rm")') == '"a \\"quoted\\" \\\\ word)(system \\"rm\\")"'
    with pytest.raises(FestivalError) as err:
        Festival("festival:kal_diphone) (system \"ls\"")
    assert "letters, digits" in str(err.value) and "\n" not in str(err.value)
    if shutil.which("festival"):
        with pytest.raises(FestivalError) as err:
            Festival("festival:no_such_voice").synthesize("bin blue")
        assert "no voice 'no_such_voice'" in str(err.value) and "\n" not in str(err.value)


def test_visemes_are_distinct_mouth_shapes(head_model):
    assert viseme_of("p") == viseme_of("m") == "pbm" and viseme_of("u:") == "w" and viseme_of("_:") == "sil"
    m = phoneme_to_viseme_matrix()
    assert m.shape == (len(PHONEMES), len(NAMES)) and (m.sum(1) == 1).all()
    basis = viseme_basis(head_model)
    feats = mouth_features(basis) - mouth_features(basis)[0]  # width, upper lip, opening (mm) vs the neutral face
    open_, pbm, w, spread = (feats[NAMES.index(n)] for n in ("open", "pbm", "w", "spread"))
    assert open_[2] > 15 and pbm[2] < -2  # open jaw vs pressed lips
    assert w[0] < -8 and spread[0] > 5  # rounded narrows, spread widens


def test_lstm_model_loss_and_regulariser(head_model):
    torch.manual_seed(0)
    basis = viseme_basis(head_model)
    model = AudioToVisemes(65, len(NAMES), len(PHONEMES), basis, channels=8, hidden=16)
    weights, logits, landmarks, _ = model(torch.randn(2, 5, 25, 65))
    assert weights.shape == (2, 5, len(NAMES)) and torch.allclose(weights.sum(-1), torch.ones(2, 5))
    assert landmarks.shape == (2, 5, 68, 2)
    one_hot = torch.zeros(1, 1, len(NAMES))
    one_hot[..., NAMES.index("open")] = 1
    assert torch.allclose(model.landmarks(one_hot)[0, 0], basis[NAMES.index("open")], atol=1e-6)
    m = phoneme_to_viseme_matrix()
    target = torch.full((2, 5), PHONEMES.index("a"))
    # weights on the viseme the phoneme head believes in cost nothing in the regulariser, elsewhere they do
    good_logits = torch.full((2, 5, len(PHONEMES)), -20.0)
    good_logits[..., PHONEMES.index("a")] = 20
    w_good = torch.zeros(2, 5, len(NAMES))
    w_good[..., NAMES.index("open")] = 1
    w_bad = torch.zeros(2, 5, len(NAMES))
    w_bad[..., NAMES.index("pbm")] = 1
    lm = model.landmarks(w_good)
    _, good = speech_loss(w_good, good_logits, lm, lm, target, m, 0.1, 0.1)
    _, bad = speech_loss(w_bad, good_logits, lm, lm, target, m, 0.1, 0.1)
    assert good["reg"] == pytest.approx(0, abs=1e-6) and bad["reg"] == pytest.approx(1, abs=1e-6)


def test_seed_000_without_regularisation_has_no_phoneme_module(head_model):
    """Seed 000's baseline: no phoneme classifier at all (not the classifier with lambda2 = 0)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        noreg = compose(config_name="config", overrides=["speech_model=lstm_noreg"]).speech
        reg = compose(config_name="config", overrides=["speech_model=lstm_reg"]).speech
    assert (noreg.phoneme_head, noreg.regularize, reg.phoneme_head, reg.regularize) == (False, False, True, True)
    basis = viseme_basis(head_model)
    model = AudioToVisemes(65, len(NAMES), len(PHONEMES), basis, channels=8, hidden=16, phoneme_head=False)
    assert model.phonemes is None and not any(n.startswith("phonemes") for n, _ in model.named_parameters())
    weights, logits, landmarks, _ = model(torch.randn(1, 4, 25, 65))
    assert logits is None and landmarks.shape == (1, 4, 68, 2)
    loss, parts = speech_loss(weights, None, landmarks, landmarks + 0.01, None, phoneme_to_viseme_matrix(), 0.1, 0.1)
    assert parts["ce"] == 0.0 and parts["reg"] == 0.0 and float(loss) == pytest.approx(2 * 0.01**2, rel=1e-4)


def test_window_model_averages_overlapping_outputs():
    model = PhonemeWindowMLP(n_phonemes=5, n_outputs=3, k_x=11, k_y=5, hidden=16, dropout=0.0)
    labels = torch.tensor([0, 1, 2, 3, 4, 0, 1])
    win = model.windows(labels)
    assert win.shape == (7, 11, 5) and (win[0, :5].argmax(-1) == 0).all() and win[0, 5].argmax() == 0
    assert win[3, 5].argmax() == 3  # the centre of window t is frame t
    model.eval()
    seq = model.predict_sequence(labels)
    out = model(win).detach()
    # output j of window t is frame t - 2 + j: frame 3 is output j of window 5 - j
    expected = torch.stack([out[5 - j, j] for j in range(5)]).mean(0)
    assert torch.allclose(seq[3], expected, atol=1e-6)


def test_window_model_reads_the_papers_linguistic_indicators():
    """Seed 001: identity over spans, categories per frame, transitions between frames, checked by hand on
    'm a' padded with silence; the model trains on them (default) and one-hot stays a named variant."""
    from avatarlab.speech.linguistic import CATEGORIES, CLASSES, SPANS, linguistic_size

    model = PhonemeWindowMLP(len(PHONEMES), 3, k_x=5, k_y=3, hidden=8, dropout=0.0, inputs="linguistic")
    m, a = PHONEMES.index("m"), PHONEMES.index("a")
    x = model.windows(torch.tensor([m, m, a]))  # window of frame 1: [_, m, m, a, _]
    n_p, n_c, cats = len(PHONEMES), len(CATEGORIES), list(CATEGORIES)
    assert x.shape == (3, linguistic_size(5)) and set(x.unique().tolist()) == {0.0, 1.0}
    identity, rest = x[1, :5 * n_p].reshape(5, n_p), x[1, 5 * n_p:]
    assert identity.argmax(1).tolist() == [0, m, m, a, 0]
    spans, rest = rest[:2 * n_p].reshape(2, n_p), rest[2 * n_p:]  # span 3 (5 is the whole window here) + window
    assert SPANS[0] == 3 and spans[0].nonzero().flatten().tolist() == sorted([m, a])
    assert spans[1].nonzero().flatten().tolist() == sorted([0, m, a])
    per_frame, moves = rest[:5 * n_c].reshape(5, n_c), rest[5 * n_c:].reshape(4, 7)
    named = [{cats[i] for i in row.nonzero().flatten().tolist()} for row in per_frame]
    assert {"nasal", "bilabial", "consonant", "voiced", "viseme_pbm"} <= named[1] and "vowel" not in named[1]
    assert {"vowel", "open_vowel", "viseme_open"} <= named[3] and named[0] == {"silence", "viseme_sil"}
    # transitions: change flag, then (from, to) over CLASSES = silence, vowel, consonant without a == b
    pairs = [(a_, b_) for a_ in range(3) for b_ in range(3) if a_ != b_]
    expect = [(0, 2), None, (2, 1), (1, 0)]  # _->m, m->m, m->a, a->_
    for k, pair in enumerate(expect):
        assert moves[k, 0] == (pair is not None)
        assert moves[k, 1:].nonzero().flatten().tolist() == ([pairs.index(pair)] if pair else []), (k, CLASSES)
    assert model(x).shape == (3, 3, 3)
    with pytest.raises(ValueError, match="linguistic inputs describe"):
        PhonemeWindowMLP(5, 3, inputs="linguistic")
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        assert compose(config_name="config", overrides=["speech_model=window"]).speech.window_inputs == "linguistic"


def test_speech_baselines_score_a_still_mouth_and_a_phoneme_lookup():
    """The trivial predictors of the lip error, on made-up faces whose mouth opens by a fixed amount on phoneme 1:
    the lookup is exact, a still mouth is not, and a model is judged on the motion alone (its face may differ)."""
    from avatarlab.speech.lip_metrics import LIPS, baseline_scores, motion_only, trivial_predictions

    rng = np.random.default_rng(0)

    def utterance(labels):
        face = rng.normal(size=(68, 2))  # another speaker's face each time
        face[36], face[45] = [-1.0, 0.0], [1.0, 0.0]  # inter-ocular distance 2
        frames = np.repeat(face[None], len(labels), 0)
        frames[np.asarray(labels) == 1, LIPS[0]:, 1] += 0.2  # the mouth moves on phoneme 1
        return {"landmarks": frames, "labels": np.asarray(labels)}

    train = [utterance([0, 1, 1, 0]), utterance([1, 0, 0, 1])]
    test = [utterance([0, 0, 1, 1, 1, 0])]
    truth = test[0]["landmarks"]
    predictions = trivial_predictions(train, test)
    assert np.allclose(motion_only(predictions["phoneme_mean"], [truth]), truth)  # the lookup is exact here
    scores = baseline_scores(train, test, model_error=1.0)
    # a still mouth at the mean: off by 0.2 * 1/2 on each frame -> 0.1 / 2 = 5 % of the inter-ocular distance
    assert scores["baselines"]["still_mouth"] == pytest.approx(5.0) and scores["baselines"]["phoneme_mean"] < 1e-6
    assert scores["best_baseline"] == "phoneme_mean" and scores["gain_over_best_baseline"] == pytest.approx(-1.0)
    audio_only = baseline_scores(train, test, model_error=1.0, fair=("still_mouth",))
    assert audio_only["best_baseline"] == "still_mouth" and audio_only["gain_over_best_baseline"] == pytest.approx(4.0)
    other_face = truth + np.array([0.5, -0.3])  # right motion, wrong place: no motion error
    assert lip_error_percent(motion_only([other_face], [truth]), truth) == pytest.approx(0.0, abs=1e-9)


def test_procrustes_alignment_and_lip_metric():
    rng = np.random.default_rng(0)
    ref = rng.normal(size=(68, 2))
    ref[36], ref[45] = [-1, 0], [1, 0]
    ang = np.radians(25)
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    moved = 1.7 * ref @ rot.T + [3, -2]
    aligned = align_to(moved[None], ref)[0]
    assert np.abs(aligned - ref).max() < 1e-9
    off = ref.copy()
    off[48:68, 1] += 0.02  # lips 1 % of the eye distance (2) off
    assert lip_error_percent(off[None], ref[None]) == pytest.approx(1.0)


def test_grid_clip_has_audio_features():
    clip = SHARED_DATA / "grid" / "bbaf2n.mpg"
    if not clip.is_file():
        pytest.skip(f"{clip} is absent")
    import subprocess

    import imageio_ffmpeg

    proc = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-i", str(clip), "-f", "s16le",
                           "-ac", "1", "-ar", "25000", "-"], capture_output=True, check=True)
    audio = np.frombuffer(proc.stdout, np.int16).astype(np.float32) / 32768
    assert abs(len(audio) / 25000 - 3.0) < 0.1
    win = windows(audio, 25000, 75, FeatureSpec())
    assert win.shape == (75, 25, 65) and np.isfinite(win).all()


def test_grid_names_and_dtw():
    from avatarlab.speech.grid import dtw_path, sentence

    assert sentence("bbaf2n") == "bin blue at f two now" and sentence("swwp2s") == "set white with p two soon"
    with pytest.raises(ValueError, match="qbaf2n"):
        sentence("qbaf2n")
    rng = np.random.default_rng(0)
    a = rng.normal(size=(30, 4))
    b = np.concatenate([np.repeat(a[:1], 10, 0), a])  # the same sequence after 10 frames of its first frame
    path = dtw_path(a, b)
    assert tuple(path[0]) == (0, 0) and tuple(path[-1]) == (29, 39)
    assert all(j == i + 10 for i, j in path if i > 0)


@needs_espeak
def test_derived_alignment_matches_grids_own_on_the_clip_that_has_one():
    clip = SHARED_DATA / "grid" / "swwp2s.mpg"
    if not clip.is_file():
        pytest.skip(f"{clip} is absent")
    from avatarlab.speech.grid import align_phonemes, read_audio, sentence
    from avatarlab.speech.tts import Espeak

    spec = FeatureSpec()
    audio = read_audio(clip, spec.sample_rate)
    _, words = align_phonemes(audio, sentence(clip.stem), Espeak(), spec)
    truth = [(w, int(s) / 25000) for s, _, w in (line.split() for line in
                                                 clip.with_suffix(".align").read_text().splitlines()) if w != "sil"]
    assert [w for w, _ in words] == [w for w, _ in truth]
    errors_ms = [1000 * abs(a - b) for (_, a), (_, b) in zip(words, truth)]
    assert np.mean(errors_ms) < 80, errors_ms  # measured: 32 ms


def test_rig_retargeting_weights_follow_seed_001():
    from avatarlab.speech.train import retarget

    poses = np.zeros((4, 2, 3), np.float32)
    poses[0, 0] = [1, 0, 0]  # +3 sigma of component 0
    poses[0, 1] = [0, 1, 0]  # -3 sigma of component 0
    poses[1, 0] = [0, 0, 1]
    coef = np.array([[3.0, 0, 0, 0], [-1.5, 0, 0, 0], [0, 1.5, 0, 0], [0, -3, 0, 0]])
    rig = retarget(coef, poses)
    assert rig[0] == pytest.approx([1, 0, 0]) and rig[1] == pytest.approx([0, 0.5, 0])
    assert rig[2] == pytest.approx([0, 0, 0.5]) and rig[3] == pytest.approx([0, 0, 0])  # -: pose 1,1 is zero here


def test_augmented_audio_has_the_asked_noise_and_keeps_its_length():
    from omegaconf import OmegaConf

    from avatarlab.speech.augment import add_noise, augment, reverberate

    rng = np.random.default_rng(0)
    clean = np.sin(2 * np.pi * 200 * np.arange(25_000) / 25_000).astype(np.float32)
    noisy = add_noise(clean, 10.0, rng, coloured=True)
    snr = 10 * np.log10(np.mean(clean.astype(np.float64) ** 2) / np.mean((noisy - clean) ** 2))
    assert snr == pytest.approx(10.0, abs=0.01)
    click = np.zeros(5000)
    click[100] = 1.0
    wet = reverberate(click, 25_000, 0.1, 0.0, rng)  # direct and reverberant energy equal: 0 dB
    tail = np.sum(wet[101:] ** 2) / wet[100] ** 2
    assert np.abs(wet[:100]).max() < 1e-12 and tail == pytest.approx(1.0, rel=1e-6) and np.abs(wet).max() == pytest.approx(1.0)
    settings = OmegaConf.load(REPO / "conf" / "config.yaml").speech.augment
    a = augment(clean, 25_000, np.random.default_rng(1), settings)
    b = augment(clean, 25_000, np.random.default_rng(1), settings)
    c = augment(clean, 25_000, np.random.default_rng(2), settings)
    assert a.dtype == np.float32 and len(a) == len(clean) and np.array_equal(a, b) and not np.allclose(a, c)
    assert np.corrcoef(a, clean)[0, 1] > 0.2  # still the same sound
    from avatarlab.runtime.errors import ConfigError
    from avatarlab.speech.augment import check_settings

    check_settings(settings)
    with pytest.raises(ConfigError, match="speech.augment: snr_db out of range"):
        check_settings(OmegaConf.merge(settings, {"snr_db": [35, 5]}))
    with pytest.raises(ConfigError, match="missing gain"):
        check_settings(OmegaConf.masked_copy(settings, [k for k in settings if k != "gain"]))


@needs_espeak
def test_real_clips_can_be_limited_per_speaker(tmp_path):
    from avatarlab.speech.real_eval import clip_paths

    for speaker, names in (("grid", "cab"), ("obama", "yx")):
        (tmp_path / speaker).mkdir()
        for n in names:
            (tmp_path / speaker / f"{n}.mp4").touch()
    patterns = [str(tmp_path / "grid" / "*.mp4"), str(tmp_path / "obama" / "*.mp4")]
    assert [p.name for p in clip_paths(patterns)] == ["a.mp4", "b.mp4", "c.mp4", "x.mp4", "y.mp4"]
    assert [f"{p.parent.name}/{p.name}" for p in clip_paths(patterns, 2)] == [
        "grid/a.mp4", "grid/b.mp4", "obama/x.mp4", "obama/y.mp4"]


def test_loudness_predictors_cover_the_frame_and_the_models_window():
    """Loudness of a clip that sounds only in [1.00, 1.04) s: the frame predictor rises at frame 25 alone, the window
    predictor at every frame whose window (250 ms ending 130 ms after the frame) overlaps that span: 22..28."""
    from avatarlab.speech.real_eval import loudness, loudness_predictors

    rate = 25_000
    audio = np.zeros(2 * rate, np.float32)
    audio[rate:rate + rate // 25] = 0.5  # a constant: RMS 0.5
    pred = loudness_predictors(audio, 50, FeatureSpec(sample_rate=rate))
    quiet = np.log(1e-4)
    assert np.flatnonzero(pred["loudness_frame"] > quiet + 1).tolist() == [25]
    assert pred["loudness_frame"][25] == pytest.approx(np.log(0.5 + 1e-4), abs=1e-5)
    assert np.flatnonzero(pred["loudness_window"] > quiet + 1).tolist() == list(range(22, 29))
    # frame 25's window is 250 ms, 40 of them loud: RMS 0.5 * sqrt(40 / 250)
    assert pred["loudness_window"][25] == pytest.approx(np.log(0.5 * np.sqrt(40 / 250) + 1e-4), abs=1e-4)
    assert loudness(audio, rate, 3, 5000, 6000).tolist() == [pytest.approx(quiet)] * 3  # past the clip's end


def test_opening_timing_scores_the_mouths_rhythm_beside_loudness():
    """A prediction that opens with the truth has r = 1, a still one r = 0, a late one less; loudness that follows
    the truth's rhythm is the baseline the gains are paired against, per clip."""
    from avatarlab.speech.lip_metrics import correlation, mouth_opening
    from avatarlab.speech.real_eval import RealClip, opening_timing

    rng = np.random.default_rng(0)
    clips, late = [], []
    for k in range(4):
        gap = np.clip(np.sin(np.linspace(0, 6 + k, 60)), 0, None) + 0.05 * rng.standard_normal(60)
        truth = np.zeros((60, 68, 2), np.float32)
        truth[:, 62, 1], truth[:, 66, 1] = gap / 2, -gap / 2
        loud = {"loudness_frame": gap + 0.5 * rng.standard_normal(60), "loudness_window": rng.standard_normal(60)}
        clips.append(RealClip(f"c{k}", "spk", np.zeros(1, np.float32), np.zeros((60, 1, 65), np.float32), truth,
                              60, 60, loudness=loud))
        late.append(np.roll(truth, 3, axis=0))
    np.testing.assert_allclose(mouth_opening(clips[0].truth), clips[0].truth[:, 62, 1] - clips[0].truth[:, 66, 1])
    exact = opening_timing([c.truth for c in clips], clips)
    assert exact["model_r"] == pytest.approx(1.0) and exact["best_baseline"] == "loudness_frame"
    base = [correlation(c.loudness["loudness_frame"], mouth_opening(c.truth)) for c in clips]
    assert exact["baselines_r"]["loudness_frame"] == pytest.approx(np.mean(base))
    assert exact["gain_mean_per_clip"] == pytest.approx(1 - np.mean(base)) and exact["wins"] == 4
    assert exact["beats_best_baseline"] == (exact["gain_mean_per_clip"] - exact["gain_ci95"] > 0)
    still = opening_timing([np.repeat(c.truth.mean(0, keepdims=True), 60, 0) for c in clips], clips)
    assert still["model_r"] == 0.0 and still["wins"] == 0 and not still["beats_best_baseline"]
    shifted = opening_timing(late, clips)
    assert 0 < shifted["model_r"] < exact["model_r"]
    assert shifted["per_clip"]["c0"]["model_r"] == pytest.approx(
        correlation(mouth_opening(late[0]), mouth_opening(clips[0].truth)))


def test_real_clip_evaluation_scores_models_beside_a_still_mouth(tmp_path, head_model):
    """GRID and Obama clips (one without audio: skipped), a model with a phoneme head; every row's still mouth
    is the clip's mean shape scored on its own frames, the adapted models differ from the synthetic one."""
    clips = [SHARED_DATA / "grid" / "bbaf2n.mpg", SHARED_DATA / "grid" / "swwp2s.mpg",
             SHARED_DATA / "obama" / "wa_working_families.mp4", SHARED_DATA / "obama" / "wa_past_few_years.mp4",
             SHARED_DATA / "obama" / "wa_young_americans.mp4"]
    if not all(c.is_file() for c in clips):
        pytest.skip("../shared/data/grid or obama clips are absent")
    from helpers.config import step_cfg

    from avatarlab.speech import real_eval

    torch.manual_seed(0)
    model = AudioToVisemes(65, len(NAMES), len(PHONEMES), viseme_basis(head_model), channels=8, hidden=16)
    path = tmp_path / "lstm_reg" / "model.pt"
    path.parent.mkdir()
    torch.save({"model": model.state_dict(), "kind": "lstm", "n_features": 65, "channels": 8, "hidden": 16,
                "phoneme_head": True}, path)
    cfg = step_cfg(real_eval, ["scale=smoke", f"speech.real_clips=[{','.join(map(str, clips))}]",
                               f"speech.real_models=[{path}]", "speech.adapt_epochs=2", "speech.adapt_seeds=2"])
    report = real_eval.run(cfg)
    assert report["skipped"] == [str(clips[-1])]
    by_name = {c["clip"]: c for c in report["clips"]}
    assert set(by_name) == {c.stem for c in clips[:4]}
    assert by_name["wa_working_families"]["video_frames"] == 61  # 29.97 fps -> 25 fps
    assert by_name["wa_working_families"]["frames_25fps"] == int(np.floor(60 / 29.97 * 25)) + 1
    assert by_name["swwp2s"]["word_start_error_ms"] < 80 and by_name["bbaf2n"]["word_start_error_ms"] is None
    assert all(c["faces_found"] == c["video_frames"] for c in report["clips"])
    speakers = report["models"]["lstm_reg"]["speakers"]
    assert set(speakers) == {"grid", "obama"}
    for speaker, rows in speakers.items():
        assert set(rows) == {"synthetic", "adapted_other_clips", "adapted_other_speakers"}
        still = {r["still_mouth_percent"] for r in rows.values()}
        assert len(still) == 1 and 0.5 < still.pop() < 10  # the same baseline for every row, a plausible size
        for r in rows.values():
            per = r["per_clip"]
            assert r["clips"] == 2 and r["wins"] == sum(v["lip_error_percent"] < v["still_mouth_percent"]
                                                        for v in per.values())
            gains = [v["still_mouth_percent"] - v["lip_error_percent"] for v in per.values()]
            assert r["gain_mean_per_clip"] == pytest.approx(np.mean(gains))
            assert r["beats_still_mouth"] == (r["gain_mean_per_clip"] - r["gain_ci95"] > 0)
        assert rows["adapted_other_clips"]["lip_error_percent"] != rows["synthetic"]["lip_error_percent"]
        assert "fine_tuning_seeds" not in rows["synthetic"]  # nothing fine-tuned, nothing to repeat
        for key in ("adapted_other_clips", "adapted_other_speakers"):  # two fine-tuning seeds: the row is the first
            spread = rows[key]["fine_tuning_seeds"]
            assert spread["seeds"] == 2 and spread["gain_mean_per_clip"][0] == rows[key]["gain_mean_per_clip"]
            assert spread["lip_error_percent"][0] == rows[key]["lip_error_percent"]
            assert spread["gain_mean_per_clip"][1] != spread["gain_mean_per_clip"][0], "a second seed, a new fine-tune"
            assert spread["beats_still_mouth"] == sum(g - h > 0 for g, h in zip(spread["gain_mean_per_clip"],
                                                                                 spread["gain_ci95"]))
            assert len(spread["opening_r"]) == 2 and spread["opening_r"][0] == rows[key]["opening_timing"]["model_r"]
        for r in rows.values():  # the opening's timing beside loudness, on the same clips
            t = r["opening_timing"]
            assert set(t["per_clip"]) == set(r["per_clip"]) and -1 <= t["model_r"] <= 1
            assert set(t["baselines_r"]) == {"loudness_frame", "loudness_window"}
            best = t["baselines_r"][t["best_baseline"]]
            assert best == max(t["baselines_r"].values()) and -1 <= best <= 1
            assert t["gain_mean_per_clip"] == pytest.approx(t["model_r"] - best)
    assert 0 <= speakers["grid"]["synthetic"]["phoneme_accuracy_vs_alignment"] <= 1
    assert "phoneme_accuracy_vs_alignment" not in speakers["obama"]["synthetic"]  # no sentence to align
    # the report's speech table: one row per model, speaker and row kind, as trained first, beside the still mouth
    from avatarlab.report.build import speech_table
    from avatarlab.runtime.io import write_json

    write_json(tmp_path / "results" / "speech" / "real_eval.json", report)
    real_rows = [r for r in speech_table(ResultsTree(tmp_path / "results"), "smoke").rows if "real" in str(r.get("data"))]
    assert len(real_rows) == 6 and "trained on the synthetic corpus" in real_rows[0]["method"]
    first = speakers["grid"]["synthetic"]
    assert real_rows[0]["data"] == "2 real grid clips" and real_rows[0]["baseline_iod"] == first["still_mouth_percent"]
    assert real_rows[0]["gain_iod"] == pytest.approx(first["still_mouth_percent"] - first["lip_error_percent"])
    assert real_rows[0]["fine_tuning_seeds"] is None  # as trained: one model, no fine-tuning seeds
    tuned = speakers["grid"]["adapted_other_clips"]["fine_tuning_seeds"]
    low, high = sorted(tuned["gain_mean_per_clip"])
    assert real_rows[1]["fine_tuning_seeds"] == (f"{low:+.2f} to {high:+.2f} over 2 seeds, "
                                                 f"{tuned['beats_still_mouth']} beyond the CI")
    from avatarlab.report.build import speech_timing_table

    timing_rows = speech_timing_table(ResultsTree(tmp_path / "results")).rows
    assert len(timing_rows) == 6 and timing_rows[0]["opening_r"] == first["opening_timing"]["model_r"]
    assert timing_rows[0]["verdict"] in {"better", "worse", "within the clips' spread"}
