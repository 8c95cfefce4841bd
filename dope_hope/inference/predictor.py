"""DopePredictor: an image (+ K, optional depth) -> mesh-frame 6-DoF detections of one object.

One predictor owns one network (one object class per model, as DOPE); several predictors can
run on one image (:func:`predict_many`). The pipeline of :meth:`DopePredictor.predict`:

1. **Image** (:mod:`~dope_hope.preprocess`): layout, working size and letterbox.
   ``height=None`` (default) fits the image inside the checkpoint's training input size;
   official DOPE weights (legacy frame) and models without a recorded input size use height
   400, the official DOPE inference height. A backend with a fixed input size
   (``fixed_input_hw``) gets the image fitted inside and padded up to it.
2. **Maps** from the backend (:class:`~dope_hope.inference.backends.MapBackend`, last stage),
   normalized with the model's recorded mean/std.
3. **Decode and PnP** in network-image pixels with ``K_net``, so the pixel thresholds mean
   the same whatever the original resolution. ``pose_search="hypotheses"`` (default): each
   centroid keeps every corner peak whose affinity points at it
   (:func:`dope_hope.maps.decode.corner_candidates`) and
   :func:`dope_hope.inference.pnp.solve_pnp_candidates` finds the pose that explains most of
   them (:func:`dope_hope.inference.pnp.solve_pnp_instances`: the peaks an accepted pose holds
   are no candidates of the centroids searched after it); two centroids explaining the same
   peaks give one detection, the higher-scoring.
   ``pose_search="groups"``: DOPE's decoding, one corner per type and centroid
   (:func:`dope_hope.maps.decode.decode_maps`), then :func:`dope_hope.inference.pnp.solve_pnp`.
   The cuboid is the model's: the checkpoint's size (mesh frame) or, with ``mesh=``, the
   mesh's own bounding box (size and centre; a size differing from the checkpoint's by more
   than 25 % is refused as a unit mistake). **Legacy frame** (official HOPE weights): PnP runs
   on the legacy cuboid and the rotation is converted with
   :func:`geometry.legacy_rotation_to_mesh`, so every returned pose is a mesh-frame pose.
4. **Back to the original image**: keypoints ``u = (u' + 0.5) / s - 0.5``; the pose needs no
   change (K_net and K describe the same camera).
5. **Depth line search** ("-LS", optional, :func:`dope_hope.refine.line_search.depth_line_search`)
   with the original K and a depth image of the original size. Model points: ``ls_points``
   farthest-point samples of the mesh surface when ``mesh=`` is given, else of the cuboid's
   surface (for a non-box object the box's front face lies in front of the real surface, which
   biases the distance: pass the mesh for non-box objects).
6. **Depth ICP** (optional, ``icp=True``, :func:`dope_hope.refine.icp.icp_refine`): after the
   line search, point-to-plane ICP of ``icp_points`` model points against the depth under the
   object refines all six DoF; kept only when it does not fit the depth worse and keeps to the
   object's own depth support (the detected region: the silhouette of the pose before any
   depth step). Without ``mesh=`` only the catalog's boxes are allowed. When the line search
   refused, the ICP stage first repeats it over :data:`ICP_LS_SEARCH`; that pose too is kept
   only within the object's own depth support (a box hidden behind a board is not moved onto
   the board).
"""
from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from dope_hope.errors import ConfigError, ModelFileError, UnknownObjectError
from dope_hope.geometry import (
    LEGACY_KEYPOINT_ORDER,
    LEGACY_TO_MESH,
    NUM_KEYPOINTS,
    cuboid_keypoints,
    legacy_keypoints_to_current,
    legacy_rotation_to_mesh,
    project_points,
    project_points_poses,
    projected_bbox,
    projected_bboxes,
)
from dope_hope.inference.backends import MapBackend, model_min_score, open_backend
from dope_hope.inference.options import InferenceOptions
from dope_hope.inference.detection import Detection
from dope_hope.inference.pnp import PoseEstimate, solve_pnp, solve_pnp_instances
from dope_hope.maps.decode import corner_candidates, decode_maps
from dope_hope.preprocess import (
    NetworkInput,
    check_intrinsics,
    prepare_input,
    to_rgb8,
    working_size,
)
from dope_hope.refine.depth import DepthImage
from dope_hope.refine.icp import icp_refine
from dope_hope.refine.line_search import depth_line_search


#: Scale range of the line search the ICP stage repeats when the default one refused.
ICP_LS_SEARCH = (0.5, 2.0)


# ----------------------------------------------------------------------------- predictor
class DopePredictor:
    """A network for one object and everything to turn images into :class:`Detection` s.

    Args:
        weights: a dope-hope checkpoint (``.pth``/``.pt``), an exported ``.onnx`` model, or a
            ready :class:`MapBackend` instance.
        backend: "auto" (ONNX for ``.onnx``, else torch), "torch" or "onnx".
        device: torch device, or "cuda..." to ask onnxruntime for its CUDA provider.
        threads: CPU threads (torch.set_num_threads / onnxruntime intra-op threads).
        mesh: optional mesh file (or loaded ``trimesh.Trimesh`` in metres) of the object: its
            box replaces the checkpoint's cuboid and its surface feeds the depth steps.
        mesh_units: units of the mesh file ("m", "cm", "mm"; default by suffix).
        options: :class:`~dope_hope.inference.options.InferenceOptions`, or a mapping of
            overrides of the packaged defaults (``dope_hope/configs/infer.yaml``).
        **overrides: single options on top (``height=400``, ``icp=True``, ``pnp={...}``, ...);
            an unknown name is a ConfigError.

    ``min_score``: when neither ``options`` nor ``overrides`` gives one, the model's own
    threshold when its file records one (``ModelInfo.min_score``), else the packaged default.
    """

    def __init__(
        self,
        weights: str | os.PathLike | MapBackend,
        backend: str = "auto",
        device: str = "cpu",
        threads: int | None = None,
        mesh: Any = None,
        mesh_units: str | None = None,
        options: InferenceOptions | Mapping[str, Any] | None = None,
        **overrides: Any,
    ):
        if isinstance(options, InferenceOptions):
            options = options.to_dict()
        given = {**(options or {}), **overrides}
        InferenceOptions.from_mapping(given)  # a bad option is refused before a model loads
        if isinstance(weights, (str, os.PathLike)):
            self.backend: MapBackend = open_backend(weights, backend, device, threads)
        elif hasattr(weights, "run") and hasattr(weights, "stride"):
            self.backend = weights
        else:
            raise ConfigError(f"weights must be a file path or a MapBackend, got {type(weights).__name__}")
        b = self.backend
        self.options = InferenceOptions.from_mapping(given, model_min_score=model_min_score(b))
        self.class_name = str(b.class_name)
        self.legacy = b.frame == "legacy" or b.keypoint_order == LEGACY_KEYPOINT_ORDER
        self.mean = tuple(float(v) for v in b.mean)
        self.std = tuple(float(v) for v in b.std)
        self.stride = int(b.stride)
        self.mesh = None
        size = np.asarray(b.size_m, dtype=np.float64).reshape(3)
        center = np.zeros(3)
        if mesh is not None:
            self.mesh, size, center = self._load_mesh(mesh, mesh_units, size)
        self.cuboid_size_m = size
        self.cuboid_center_m = center
        if self.options.icp and self.mesh is None:
            self._check_icp_surface()
        #: (9, 3) mesh-frame cuboid keypoints, current order.
        self.cuboid_mesh = cuboid_keypoints(size, center)
        if self.legacy:
            # The same box in the legacy frame (p_legacy = L^T p_mesh), listed in the legacy
            # order: corner k at CUBOID_CORNER_SIGNS[k] * legacy extents / 2.
            size_leg = np.abs(LEGACY_TO_MESH).T @ size
            self.cuboid_pnp = cuboid_keypoints(size_leg, LEGACY_TO_MESH.T @ center)
        else:
            self.cuboid_pnp = self.cuboid_mesh
        self._model_points: np.ndarray | None = None
        self._bbox_points: np.ndarray | None = None
        self._icp_model: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------ setup helpers
    def _load_mesh(self, mesh: Any, units: str | None, ckpt_size: np.ndarray):
        from dope_hope.io.meshes import check_mesh_box, load_mesh, mesh_cuboid

        source = "<mesh>"
        if isinstance(mesh, (str, os.PathLike)):
            source = str(mesh)
            mesh = load_mesh(mesh, units=units)
        size, center = mesh_cuboid(mesh)
        check_mesh_box(size, ckpt_size, source, self.class_name, "the model's cuboid")
        return mesh, size, center

    def _surface(self):
        """The mesh, else the cuboid's surface (see the module docstring), metres."""
        if self.mesh is not None:
            return self.mesh
        import trimesh

        box = trimesh.creation.box(extents=self.cuboid_size_m)
        box.apply_translation(self.cuboid_center_m)
        return box

    def _check_icp_surface(self) -> None:
        """Without a mesh ICP fits the cuboid's surface to the depth: right for a box only."""
        from dope_hope.catalog import get_object

        try:
            category = get_object(self.class_name).category
        except UnknownObjectError:
            category = "object outside the HOPE catalog"
        if category != "cuboid":
            raise ConfigError(f"ICP for {self.class_name} ({category}) needs its mesh (mesh= / --mesh): "
                              "without one it would fit the cuboid's surface, which is right for boxes only")

    @property
    def model_points(self) -> np.ndarray:
        """(ls_points, 3) mesh-frame surface points for the line search, metres (cached)."""
        if self._model_points is None:
            from dope_hope.io.meshes import sample_surface_points

            self._model_points = sample_surface_points(self._surface(), self.options.ls_points, seed=0)
        return self._model_points

    @property
    def bbox_points(self) -> np.ndarray:
        """(N, 3) mesh-frame points whose projection bounds the object, metres: the mesh's
        convex hull vertices, else the cuboid's 8 corners (cached)."""
        if self._bbox_points is None:
            if self.mesh is not None:
                self._bbox_points = np.asarray(self.mesh.convex_hull.vertices, dtype=np.float64)
            else:
                self._bbox_points = self.cuboid_mesh[:NUM_KEYPOINTS - 1].copy()
        return self._bbox_points

    @property
    def icp_model(self) -> tuple[np.ndarray, np.ndarray]:
        """((icp_points, 3) mesh-frame surface points, metres; their (icp_points, 3) unit
        normals) for ICP (cached)."""
        if self._icp_model is None:
            from dope_hope.io.meshes import sample_surface_points

            if self.mesh is None:
                self._check_icp_surface()
            self._icp_model = sample_surface_points(self._surface(), self.options.icp_points, seed=0,
                                                    oversample=10, return_normals=True)
        return self._icp_model

    def working_size(self, image_hw: tuple[int, int]) -> tuple[tuple[int, int], tuple[int, int]]:
        """((H', W') resized content, (Hp, Wp) padded network input) for an image of (H, W)
        (:func:`dope_hope.preprocess.working_size` with this model's sizes)."""
        return working_size(image_hw, height=self.options.height, input_hw=getattr(self.backend, "input_hw", None),
                            fixed_input_hw=getattr(self.backend, "fixed_input_hw", None), legacy=self.legacy)

    # ------------------------------------------------------------------ inference
    def prepare(self, image: np.ndarray) -> NetworkInput:
        """Image of any layout -> :class:`NetworkInput` at the working size."""
        rgb = to_rgb8(image)
        resized, padded = self.working_size(rgb.shape[:2])
        return prepare_input(rgb, resized, self.mean, self.std, padded)

    def infer_maps(self, image: np.ndarray | NetworkInput) -> tuple[np.ndarray, np.ndarray, NetworkInput]:
        """Run the network: (belief (9, h, w), affinity (16, h, w), the NetworkInput)."""
        net_in = image if isinstance(image, NetworkInput) else self.prepare(image)
        belief, affinity = self.backend.run(net_in.batch)
        belief, affinity = np.asarray(belief)[0], np.asarray(affinity)[0]
        Hp, Wp = net_in.batch.shape[2:]
        if belief.shape != (NUM_KEYPOINTS, Hp // self.stride, Wp // self.stride) or \
                affinity.shape != (2 * (NUM_KEYPOINTS - 1),) + belief.shape[1:]:
            raise ModelFileError(getattr(self.backend, "source", "<model>"),
                                 f"network returned maps {belief.shape} / {affinity.shape} for an "
                                 f"input of {Hp}x{Wp} at stride {self.stride}")
        return belief, affinity, net_in

    def predict(self, image: np.ndarray, K: np.ndarray, depth: np.ndarray | DepthImage | None = None,
                depth_scale_m: float = 0.001, calibration: float = 1.0) -> list[Detection]:
        """Detect this predictor's object in one image.

        Args:
            image: (H, W[, C]) RGB image array (see :func:`to_rgb8`).
            K: (3, 3) intrinsics of ``image``.
            depth: optional (H, W) depth registered to the image: integer units of
                ``depth_scale_m`` metres, or float metres, or a ready
                :class:`~dope_hope.refine.depth.DepthImage`; enables the line search.
            depth_scale_m: metres per integer depth unit (0.001 = millimetres).
            calibration: depth multiplier (raw RealSense captures of the HOPE setup:
                :data:`dope_hope.refine.depth.HOPE_REALSENSE_DEPTH_CALIBRATION`; the HOPE
                dataset's depth images already include it).

        Returns:
            Detections sorted by decreasing score, mesh-frame poses.
        """
        K = check_intrinsics(K)
        belief, affinity, net_in = self.infer_maps(image)
        depth = as_depth_image(depth, K, depth_scale_m, calibration, net_in.original_hw)
        return self.detections_from_maps(belief, affinity, net_in, K, depth)

    def detections_from_maps(self, belief: np.ndarray, affinity: np.ndarray, net_in: NetworkInput,
                             K: np.ndarray, depth: DepthImage | None = None) -> list[Detection]:
        """Decode + PnP (+ line search, ICP) the maps of :meth:`infer_maps` (see :meth:`predict`)."""
        K = check_intrinsics(K)
        K_net = net_in.network_K(K)
        mean_scale = math.sqrt(net_in.scale[0] * net_in.scale[1])
        out: list[Detection] = []
        for est in self._poses(belief, affinity, K_net):
            if est.score < self.options.min_score:
                continue
            R, t = est.R, est.t
            kp, scores, inliers = est.keypoints, est.keypoint_scores, est.inliers
            if self.legacy:
                R = legacy_rotation_to_mesh(R)
                kp = legacy_keypoints_to_current(kp)
                scores = legacy_keypoints_to_current(scores[:, None])[:, 0]
                inliers = legacy_keypoints_to_current(inliers[:, None])[:, 0]
            det = Detection(
                class_name=self.class_name, score=float(est.score), R=R, t=t.copy(),
                keypoints_2d=net_in.to_original_px(kp), keypoint_scores=np.asarray(scores, float),
                inliers=np.asarray(inliers, bool), projected_2d=np.zeros((NUM_KEYPOINTS, 2)),
                reprojection_error_px=float(est.reprojection_error_px / mean_scale),
                cuboid_size_m=self.cuboid_size_m.copy(), cuboid_center_m=self.cuboid_center_m.copy(),
            )
            if depth is not None:
                ls = depth_line_search(R, t, self.model_points, depth, **self.options.line_search)
                det.t, det.ls_applied, det.ls_reason, det.ls_scale = ls.t, ls.applied, ls.reason, ls.scale
                if self.options.icp:
                    self._refine_icp(det, depth)
            elif self.options.icp:
                det.icp_reason = "no depth image"
            out.append(det)
        if out:  # the final poses' projections, all at once
            Rs, ts = np.stack([d.R for d in out]), np.stack([d.t for d in out])
            projected = project_points_poses(self.cuboid_mesh, K, Rs, ts)
            boxes = projected_bboxes(self.bbox_points, K, Rs, ts, net_in.original_hw)
            for det, uv, box in zip(out, projected, boxes):
                det.projected_2d, det.bbox_2d = uv, box
        out.sort(key=lambda d: -d.score)
        return out

    def refine_icp(self, det: Detection, depth: DepthImage) -> Detection:
        """The ICP step of the module docstring on one detection, whatever ``icp`` was set to:
        a copy of ``det`` (as :meth:`predict` returns it with ``depth``, i.e. after the line
        search) refined by ICP against ``depth``; ``det`` itself is unchanged. Lets a caller
        keep both the -LS and the -LS + ICP pose without decoding the maps twice."""
        out = replace(det)
        self._refine_icp(out, depth)
        out.projected_2d = project_points(self.cuboid_mesh, depth.K, out.R, out.t)
        out.bbox_2d = projected_bbox(self.bbox_points, depth.K, out.R, out.t, depth.hw)
        return out

    def _refine_icp(self, det: Detection, depth: DepthImage) -> None:
        """The ICP step of the module docstring, in place on ``det`` (after the line search)."""
        points, normals = self.icp_model
        res = None
        if not det.ls_applied:  # ICP needs the depth within a few cm: a wider line search first
            options = {**self.options.line_search, "search": ICP_LS_SEARCH}
            wide = depth_line_search(det.R, det.t, self.model_points, depth, **options)
            if wide.applied:  # kept only while the object's own depth support holds it
                res = icp_refine(det.R, wide.t, points, normals, depth, initial_pose=(det.R, det.t),
                                 **self.options.icp_refine)
                search = f"search {ICP_LS_SEARCH[0]:g}-{ICP_LS_SEARCH[1]:g}, for ICP"
                if res.start_supported:
                    det.t, det.ls_applied, det.ls_scale = wide.t, True, wide.scale
                    det.ls_reason = f"ok ({search})"
                else:
                    det.ls_reason += f"; s = {wide.scale:.3f} ({search}) {res.reason.removeprefix('the start pose ')}"
                    res = None
        if res is None:
            res = icp_refine(det.R, det.t, points, normals, depth, **self.options.icp_refine)
        det.icp_applied, det.icp_reason = res.applied, res.reason
        det.icp_fit = res.fit_after if res.applied else res.fit_before
        if res.applied:
            det.R, det.t = res.R, res.t

    def _poses(self, belief: np.ndarray, affinity: np.ndarray, K_net: np.ndarray) -> list[PoseEstimate]:
        """Network-image poses of the instances in one image's maps (step 4 of the module
        docstring), best first; keypoints in the network's own order."""
        if self.options.pose_search == "groups":
            found = [solve_pnp(inst.keypoints, inst.scores, self.cuboid_pnp, K_net, **self.options.pnp)
                     for inst in decode_maps(belief, affinity, self.stride, **self.options.decode)]
            return [e for e in found if e is not None]
        candidates = corner_candidates(belief, affinity, self.stride, **self.options.decode)
        return solve_pnp_instances([(c.keypoint_ids, c.xy, c.scores) for c in candidates], self.cuboid_pnp,
                                   K_net, **self.options.hypotheses, **self.options.pnp)

    def __repr__(self) -> str:
        return (f"DopePredictor(class_name={self.class_name!r}, stride={self.stride}, "
                f"frame={'legacy' if self.legacy else 'mesh'}, height={self.options.height})")


def as_depth_image(depth: np.ndarray | DepthImage | None, K: np.ndarray, depth_scale_m: float,
                   calibration: float, image_hw: tuple[int, int]) -> DepthImage | None:
    """The predictor's depth boundary: None stays None, a raw array becomes a checked
    :class:`DepthImage` (metres, this K, the colour image's size), a DepthImage passes."""
    if depth is None or isinstance(depth, DepthImage):
        return depth
    return DepthImage.from_raw(depth, K, depth_scale_m, calibration, image_hw)


def predict_many(predictors: Sequence[DopePredictor], image: np.ndarray, K: np.ndarray,
                 depth: np.ndarray | DepthImage | None = None, depth_scale_m: float = 0.001,
                 calibration: float = 1.0,
                 on_maps: Callable[[DopePredictor, np.ndarray, np.ndarray, NetworkInput], None] | None = None,
                 ) -> list[Detection]:
    """Run several one-object predictors on one image; detections sorted by decreasing score.

    The image is converted once, and resized/normalized once per distinct working size and
    normalization (predictors with equal settings share the network input).
    ``on_maps(predictor, belief, affinity, network_input)`` is called with each model's maps
    (e.g. to draw them).
    """
    K = check_intrinsics(K)
    rgb = to_rgb8(image)
    depth = as_depth_image(depth, K, depth_scale_m, calibration, rgb.shape[:2])
    cache: dict[tuple, NetworkInput] = {}
    out: list[Detection] = []
    for p in predictors:
        resized, padded = p.working_size(rgb.shape[:2])
        key = (resized, padded, p.mean, p.std)
        if key not in cache:
            cache[key] = prepare_input(rgb, resized, p.mean, p.std, padded)
        belief, affinity, net_in = p.infer_maps(cache[key])
        if on_maps is not None:
            on_maps(p, belief, affinity, net_in)
        out.extend(p.detections_from_maps(belief, affinity, net_in, K, depth))
    out.sort(key=lambda d: -d.score)
    return out
