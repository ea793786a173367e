r"""Per-camera appearance: a learned affine colour transform of the rendered image.

Real rigs expose and white-balance every camera differently (and auto-exposure changes over time),
which a single radiance field cannot express: the Gaussians then average the cameras' colours and
every view is off. As in drivestudio's affine colour transform and gsplat's ``app_opt``, the
render of a view is corrected by a small learned transform before the colour loss, so that the
Gaussians keep one colour and the transform absorbs the camera's:

.. math::

    \hat I(p) = (I + \Delta M_c + \Delta M_{c,f})\, I_\text{render}(p) + b_c + b_{c,f}

with a 3×3 matrix and a bias per camera :math:`c` (identity and zero at the start) and, optionally,
a residual per camera and frame :math:`f` (per image, for auto-exposure).

The Gaussians' colours and the transforms are only defined together: any colour transform of the
Gaussians undone by every camera's transform renders the same images. A weak pull toward the
identity does not settle this in a finite run — early in training, while the Gaussians are still
wrong everywhere, every camera's transform absorbs part of the common error and stays there, so the
raw renders (and the exported model) drift off in colour. By default the camera transforms are
therefore *centred*: their mean over the rig is the identity
(:math:`\Delta M_c = D_c - \tfrac1C\sum_k D_k`, likewise the biases), which fixes the common
transform exactly; the Gaussians keep the rig's average colour and the transforms only express
the cameras' differences from it. (With one camera a centred transform is the identity: only
per-frame residuals remain.)

Unlike gsplat's ``app_opt`` (a per-image embedding fed with each Gaussian's features to an MLP
that predicts its colour), the transform acts on the image, has 12 numbers per camera and does not
touch the Gaussians; unlike drivestudio's (a per-image embedding decoded by an MLP into a 3×4
matrix, the mean embedding at test time), a held-out view of a known camera has a transform of its
own: the camera's. Held-out frames have no per-frame residual (it is learned only from training images),
so evaluation uses the camera's transform alone.

:func:`apply_affine` is the operation; :class:`AppearanceModel` holds the parameters;
:class:`AppearanceConfig` is the trainer's setting (``TrainConfig.appearance``, off by default).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from vadgs.checks import Checked, bool_field, check_same_device, check_shape, checked, float_field
from vadgs.data.scene import Scene

__all__ = [
    "AppearanceConfig",
    "AppearanceModel",
    "apply_affine",
    "correct_view",
    "identity_deviation",
    "view_camera",
]


def apply_affine(rgb: torch.Tensor, matrix: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    r"""Apply a colour transform :math:`M\,c + b` to every pixel of a batch of images.

    Differentiable w.r.t. ``rgb``, ``matrix`` and ``bias``. No clamping: the result may leave
    ``[0, 1]`` (the colour loss sees it as is; metrics clamp). The identity (``matrix`` = I,
    ``bias`` = 0) returns ``rgb`` bit for bit.

    Args:
        rgb: images.
        matrix: one 3×3 colour matrix per image.
        bias: one colour offset per image.

    Returns:
        The transformed images, on the device and in the dtype of ``rgb``.

    Shape:
        - rgb: :math:`(B, 3, H, W)`
        - matrix: :math:`(B, 3, 3)`
        - bias: :math:`(B, 3)`
        - output: :math:`(B, 3, H, W)`

    Example:
        >>> rgb = torch.full((1, 3, 2, 2), 0.5)
        >>> out = apply_affine(rgb, 2 * torch.eye(3)[None], torch.tensor([[0.0, 0.1, -0.5]]))
        >>> out[0, :, 0, 0]
        tensor([1.0000, 1.1000, 0.5000])
    """
    dims = check_shape(rgb, "rgb", ("B", 3, "H", "W"))
    check_shape(matrix, "matrix", ("B", 3, 3), dims)
    check_shape(bias, "bias", ("B", 3), dims)
    check_same_device(("rgb", rgb), ("matrix", matrix), ("bias", bias))
    return torch.einsum("bij,bjhw->bihw", matrix, rgb) + bias[:, :, None, None]


def identity_deviation(matrix: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    r"""Squared distance of colour transforms from the identity, :math:`\sum \|M - I\|_F^2 + \|b\|^2`.

    Differentiable w.r.t. both. The regulariser of :class:`AppearanceModel`.

    Shape:
        - matrix: :math:`(*, 3, 3)`
        - bias: :math:`(*, 3)`
        - output: scalar

    Example:
        >>> identity_deviation(torch.eye(3)[None], torch.tensor([[0.0, 0.0, 0.5]]))
        tensor(0.2500)
    """
    check_shape(matrix, "matrix", ("*", 3, 3))
    check_shape(bias, "bias", ("*", 3))
    eye = torch.eye(3, device=matrix.device, dtype=matrix.dtype)
    return ((matrix - eye) ** 2).sum() + (bias**2).sum()


@dataclass(frozen=True)
class AppearanceConfig(Checked):
    """Settings of the per-camera appearance model (``TrainConfig.appearance``).

    Attributes:
        per_frame: also learn a residual transform per camera and frame (per training image:
            auto-exposure); held-out frames use the camera's transform alone.
        centered: keep the mean camera transform at the identity (see the module docstring);
            False: free transforms, held near the identity by ``reg`` only.
        lr: Adam learning rate of the transforms (constant; their own optimizer).
        reg: weight of :func:`identity_deviation` of the view's camera transform in the loss
            (keeps the transforms near the identity).
        frame_reg: weight of the squared per-frame residual of the view (with ``per_frame``).
    """

    per_frame: bool = checked(False, bool_field())
    centered: bool = checked(True, bool_field())
    lr: float = checked(2e-3, float_field(0, lo_open=True))
    reg: float = checked(1e-3, float_field(0))
    frame_reg: float = checked(1e-2, float_field(0))


class AppearanceModel(nn.Module):
    """Learned colour transform per camera, and optionally per camera and frame; see :func:`apply_affine`.

    Parameters (all zero at construction, so the transform is the identity): ``matrix``
    ``(C, 3, 3)`` and ``bias`` ``(C, 3)``, the cameras' deviations from the identity (minus their
    mean over the cameras when ``centered``); with ``num_frames``, ``frame_matrix``
    ``(F, C, 3, 3)`` and ``frame_bias`` ``(F, C, 3)``, residuals per frame position and camera.

    Args:
        num_cameras: cameras of the rig (indices as in ``scene.camera_names``; :func:`view_camera`).
        num_frames: frame positions (``len(scene.frames)``) for per-frame residuals; None: none.
        centered: the mean of the camera transforms is the identity (see the module docstring).

    Example:
        >>> app = AppearanceModel(num_cameras=2)
        >>> rgb = torch.rand(1, 3, 4, 5)
        >>> torch.equal(app(rgb, camera=1), rgb)
        True
        >>> with torch.no_grad():
        ...     _ = app.bias[1].fill_(0.2)
        >>> app.transform(0)[1].detach(), app.transform(1)[1].detach()  # centred: mean bias 0
        (tensor([[-0.1000, -0.1000, -0.1000]]), tensor([[0.1000, 0.1000, 0.1000]]))
    """

    def __init__(self, num_cameras: int, num_frames: int | None = None, centered: bool = True) -> None:
        super().__init__()
        if int(num_cameras) < 1:
            raise ValueError(f"num_cameras: expected >= 1, got {num_cameras}")
        if num_frames is not None and int(num_frames) < 1:
            raise ValueError(f"num_frames: expected >= 1 or None, got {num_frames}")
        self.num_cameras = int(num_cameras)
        self.num_frames = None if num_frames is None else int(num_frames)
        self.centered = bool(centered)
        self.matrix = nn.Parameter(torch.zeros(self.num_cameras, 3, 3))
        self.bias = nn.Parameter(torch.zeros(self.num_cameras, 3))
        if self.num_frames is not None:
            self.frame_matrix = nn.Parameter(torch.zeros(self.num_frames, self.num_cameras, 3, 3))
            self.frame_bias = nn.Parameter(torch.zeros(self.num_frames, self.num_cameras, 3))

    @classmethod
    def from_state_dict(cls, state: dict[str, torch.Tensor], centered: bool = True) -> AppearanceModel:
        """Rebuild a model from its ``state_dict()`` (sizes read from the tensors' shapes)."""
        frames = state["frame_matrix"].shape[0] if "frame_matrix" in state else None
        model = cls(state["matrix"].shape[0], frames, centered)
        model.load_state_dict(state)
        return model

    def _check(self, camera: int, frame: int | None) -> None:
        if not 0 <= camera < self.num_cameras:
            raise ValueError(f"camera: expected an index in [0, {self.num_cameras}), got {camera}")
        if frame is not None and self.num_frames is not None and not 0 <= frame < self.num_frames:
            raise ValueError(f"frame: expected a position in [0, {self.num_frames}), got {frame}")

    def transform(self, camera: int, frame: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The colour matrix ``(1, 3, 3)`` and bias ``(1, 3)`` of a view (differentiable).

        Args:
            camera: the camera's index.
            frame: the frame position, for the per-frame residual; None (a held-out frame, or a
                model without per-frame residuals, which ignores it): the camera's transform alone.
        """
        self._check(camera, frame)
        matrix, bias = self.matrix[camera], self.bias[camera]
        if self.centered:
            matrix, bias = matrix - self.matrix.mean(0), bias - self.bias.mean(0)
        matrix = torch.eye(3, device=matrix.device, dtype=matrix.dtype) + matrix
        if frame is not None and self.num_frames is not None:
            matrix = matrix + self.frame_matrix[frame, camera]
            bias = bias + self.frame_bias[frame, camera]
        return matrix[None], bias[None]

    def penalty(self, camera: int, frame: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Regularisers of a view (differentiable).

        Returns:
            The camera transform's :func:`identity_deviation`, and the squared per-frame residual
            (0 without ``frame`` or per-frame residuals).
        """
        self._check(camera, frame)
        camera_term = identity_deviation(*self.transform(camera))
        if frame is None or self.num_frames is None:
            return camera_term, torch.zeros((), device=camera_term.device, dtype=camera_term.dtype)
        residual_m, residual_b = self.frame_matrix[frame, camera], self.frame_bias[frame, camera]
        return camera_term, (residual_m**2).sum() + (residual_b**2).sum()

    def forward(self, rgb: torch.Tensor, camera: int, frame: int | None = None) -> torch.Tensor:
        """The corrected image ``(1, 3, H, W)`` of a render ``rgb`` of the view (camera, frame).

        Differentiable w.r.t. ``rgb`` and the parameters; the parameters must be on ``rgb``'s device.
        """
        return apply_affine(rgb, *self.transform(camera, frame))

    def extra_repr(self) -> str:  # noqa: D102 (nn.Module's)
        return f"num_cameras={self.num_cameras}, num_frames={self.num_frames}, centered={self.centered}"


def view_camera(scene: Scene, view: int) -> int:
    """The camera index of a view for :class:`AppearanceModel` (its position in ``scene.camera_names``).

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path())
        >>> scene.camera_names, [view_camera(scene, v) for v in range(3)]
        (['front', 'front_left', 'front_right'], [0, 1, 2])
    """
    return scene.camera_names.index(scene.views[view].camera)


def correct_view(
    appearance: AppearanceModel | None, scene: Scene, view: int, rgb: torch.Tensor, held_out: bool = True
) -> torch.Tensor:
    """A render ``rgb`` ``(1, 3, H, W)`` of a scene view, corrected by the view's colour transform.

    Args:
        appearance: the model; None returns ``rgb`` itself.
        scene: the scene of ``view``.
        view: the view's index.
        rgb: its render.
        held_out: use the camera's transform alone (a test view: per-frame residuals exist only
            for training images); False: with the residual of the view's frame (training).

    Example:
        >>> from vadgs.data import load_scene, sample_scene_path
        >>> scene = load_scene(sample_scene_path(), scale=0.25)
        >>> rgb = torch.rand(1, 3, *scene.image_size(0))
        >>> correct_view(None, scene, 0, rgb) is rgb
        True
        >>> app = AppearanceModel(3, num_frames=len(scene.frames))
        >>> torch.equal(correct_view(app, scene, 0, rgb, held_out=False), rgb)
        True
    """
    if appearance is None:
        return rgb
    frame = None if held_out else scene.view_frame_position(view)
    return appearance(rgb, view_camera(scene, view), frame)
