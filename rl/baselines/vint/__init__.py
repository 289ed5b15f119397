"""ViNT-style baseline (trained on our data): a visual navigation transformer after ViNT (Shah et al., "ViNT: A
Foundation Model for Visual Navigation", CoRL 2023), trained by imitation on our recorded expert dataset.

The released ViNT weights cannot be downloaded here, so this is ViNT's architecture, losses and controller trained
from scratch on ``DATA_DIR/datasets/<repo_id>`` (``make record``); tables and figures call it
"ViNT-style (trained on our data)".

What it observes in our sim: the two RGB cameras (``obs["rgb_left"]``, ``obs["rgb_right"]``, yawed ±35°), each
resized to ``image_hw`` and laid side by side (left | right, the robot's view from left to right) as one image, and
the goal (or the long-horizon waypoint) as a point in the robot frame. No depth, no map, no pedestrian tracks.

Architecture (ViNT's, sizes for a 2-core CPU; ViNT's in brackets)::

    images  B x (P+1) x 3 x h x 2w  uint8, oldest first, the current frame last     (P = context = 5 past frames)
      -> obs_encoder per image: small CNN, 4 conv layers, 2 x 4 average-pooled grid   [EfficientNet-B0, global pool]
         (``encoder="efficientnet_b0"``: torchvision's EfficientNet-B0, random init, global pool, as ViNT)
      -> compress_obs_enc: Linear -> E                                                 (E = embed_dim 128 [512])
    goal    B x 3  [cos θ, sin θ, tanh(d / goal_scale_m)] of the goal point in the robot frame
      -> goal_mlp: 3 -> 64 -> E                                                         [EfficientNet on obs+goal image]
    tokens  B x (P+2) x E -> + sinusoidal positions -> transformer encoder (pre-norm, GELU, dropout 0.1)
                                                        (layers 4 [4], heads 4 [4], feed-forward 4 E [4 E])
      -> flatten -> MLP (P+2)E -> E -> 256 -> 128 -> 64 -> 32 (ReLU)                    [the same]
      -> dist_predictor 32 -> 1: temporal distance to the goal (steps)
      -> action_predictor 32 -> H x 4: per-step deltas (Δx, Δy) summed into waypoints, (cos, sin) of the yaw
         normalised to unit length                                                      (H = horizon = 5 [5])

Waypoints are in the current robot frame (x forward, y left), divided by ``metres_per_step`` =
``v_max * spacing / fps`` (0.2 m with the defaults), as ViNT divides by its data's metres per step.

Training (ViNT's losses): ``L = alpha * 1e-2 * MSE(distance) + (1 - alpha) * MSE(waypoints)`` with alpha = 0.5,
AdamW with cosine decay. Labels from the dataset: the poses ``observation.odom`` at ``t + k * spacing`` (k = 1..H)
relative to the pose at ``t`` (held at the episode's last pose past its end, ViNT's padding); the context frames
``t - j * spacing`` (j = P..1; the first frame repeated before the episode's start); the goal ``observation.goal``
in the robot frame; the distance = steps of ``spacing`` frames to the episode's end, capped at ``max_dist``.
Frames are preloaded at the reduced resolution (uint8); a batch is a few clips of consecutive targets so that each
frame is encoded once per batch. Train / validation split by episode (:func:`pretrain.data.split_episodes`);
optional left-right mirroring (images flipped and swapped, y, yaw and goal negated).

Controller (ViNT's ``pd_controller``): take predicted waypoint ``waypoint_index`` (ViNT's default 2, the third),
scale it back to metres, and with ``DT = spacing / fps`` (one waypoint step)::

    dx ≈ 0 and dy ≈ 0:  v = 0, ω = atan2(sin, cos) / DT
    dx ≈ 0:             v = 0, ω = sign(dy) π / (2 DT)
    otherwise:          v = dx / DT, ω = atan(dy / dx) / DT

clipped to the robot's limits (v ∈ [0, v_max], ω ∈ [−ω_max, ω_max]).

Deviations from ViNT, and why:

* trained from scratch on our expert dataset (about 100 episodes by default) instead of ViNT's 100 h of
  real-robot data and pretrained weights: no download is possible here; hence "ViNT-style (trained on our data)";
* a point goal (goal / waypoint in the robot frame through an MLP) instead of a goal image: our benchmark gives
  point goals; the distance head is kept (its label: steps to the episode's end);
* the default image encoder is a small CNN with a 2 x 4 pooled grid instead of EfficientNet-B0 with global
  pooling (EfficientNet-B0 is selectable): EfficientNet trains too slowly on two CPU cores, and the grid keeps
  where things are in the wide left | right image;
* E = 128 instead of 512 (CPU budget); the two cameras as one side-by-side image (ViNT has one camera);
* mirror augmentation (ViNT's data is not mirrored): it doubles our small dataset and keeps left/right balanced;
* He initialisation (zero biases) of the ReLU MLP after the transformer instead of PyTorch's default: with the
  default, most of its units started (and stayed) on or off for every input, and the trained network ignored the goal
  and drove straight (acceptance 0.00 / 0.00 / 0.06 → 0.24 / 0.46 / 0.28 on the same data and budget;
  docs/notes/2026-11-vint-does-not-learn-steering.md). Released weights overwrite it.

Released weights (:func:`load_released_weights`, ``Config.init_weights``): training starts from a state dict in
the released ``vint.pth`` layout when the model is the faithful-size variant (``encoder="efficientnet_b0"``,
``embed_dim=512``, context 5, horizon 5, 4 layers, 4 heads, feed-forward factor 4, output layers
256-128-64-32). Supported: a plain state dict (``.safetensors``, or a torch file of tensors, optionally under
``"model"`` / ``"state_dict"``). The released ``vint.pth`` pickles the whole module (it needs the authors'
``vint_train`` package to unpickle); convert it once with their code:
``torch.save(torch.load("vint.pth", weights_only=False)["model"].state_dict(), "vint_state.pth")``.
Mapped: ``obs_encoder.*`` (efficientnet_pytorch names, mapped in order onto torchvision's, shapes checked; its
``_fc`` is unused), ``compress_obs_enc``, ``decoder.*`` (positions, transformer, output MLP),
``dist_predictor``, ``action_predictor``. Not used: ``goal_encoder`` / ``compress_goal_enc`` (ViNT's image-goal
encoder; ours is a point-goal MLP, trained from its initialisation). Not identical: efficientnet_pytorch pads
stride-2 convolutions TensorFlow-style ("same", asymmetric), torchvision symmetrically, so the loaded encoder's
features differ slightly from the released model's — fine-tune (train) after loading. Not verified against the
real file (unavailable here); tested with a constructed state dict in that layout.

Layout: :mod:`~rl.baselines.vint.configuration` (options), :mod:`~rl.baselines.vint.model` (the network),
:mod:`~rl.baselines.vint.weights` (the released-weights loader), :mod:`~rl.baselines.vint.data` (labels and the
recorded dataset), :mod:`~rl.baselines.vint.training` (minibatches, losses, the train entry point),
:mod:`~rl.baselines.vint.driver` (the controller, the context buffer and the benchmark driver),
:mod:`~rl.baselines.vint.diagnose` (what a checkpoint predicts, offline on its dataset: ``python -m
rl.baselines.vint.diagnose CKPT``).
"""

from rl.baselines.vint.configuration import CAMERAS, ENCODERS, IMAGENET_MEAN, IMAGENET_STD, NAME, Config
from rl.baselines.vint.data import (
    Frames,
    check_dataset,
    context_indices,
    dataset_root,
    goal_features,
    load_dataset,
    resize_images,
    side_by_side,
    trajectory_labels,
)
from rl.baselines.vint.driver import ContextBuffer, Driver, vint_controller
from rl.baselines.vint.model import Decoder, PositionalEncoding, ViNTStyle, build_model
from rl.baselines.vint.training import Batch, Trainer, inputs, train
from rl.baselines.vint.weights import efficientnet_pytorch_b0_keys, load_released_weights

__all__ = [
    "CAMERAS", "ENCODERS", "IMAGENET_MEAN", "IMAGENET_STD", "NAME", "Batch", "Config", "ContextBuffer", "Decoder",
    "Driver", "Frames", "PositionalEncoding", "Trainer", "ViNTStyle", "build_model", "check_dataset",
    "context_indices", "dataset_root", "efficientnet_pytorch_b0_keys", "goal_features", "inputs", "load_dataset",
    "load_released_weights", "resize_images", "side_by_side", "train", "trajectory_labels", "vint_controller",
]
