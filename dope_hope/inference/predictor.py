"""DopePredictor: an image (+ K, optional depth) -> mesh-frame 6-DoF detections of a model's objects.

One predictor owns one network, of one object (as DOPE) or of several (a belief/affinity group
per object, all from one forward pass; ``classes=`` keeps a subset); several predictors can
run on one image (:func:`predict_many`). The pipeline of :meth:`DopePredictor.predict`:

1. **Image** (:mod:`~dope_hope.preprocess`): layout, working size and letterbox.
   ``height=None`` (default) fits the image inside the checkpoint's training input size;
   official DOPE weights (legacy frame) and models without a recorded input size use height
   400, the official DOPE inference height. A backend with a fixed input size
   (``fixed_input_hw``) gets the image fitted inside and padded up to it.
2. **Maps** from the backend (:class:`~dope_hope.inference.backends.MapBackend`, last stage),
   normalized with the model's recorded mean/std.
3. **Decode and PnP**, object by object (its own channel group, cuboid, mesh; a group whose
   belief maps reach the decode threshold nowhere is skipped before any decoding, so absent
   objects cost one max each; the peaks of the groups left come from one search over their
   stacked belief maps, :func:`dope_hope.maps.peaks.split_peaks`) in network-image pixels with
   ``K_net``, so the pixel thresholds mean the same whatever the original resolution.
   ``pose_search="hypotheses"`` (default): each centroid keeps every corner peak whose
   affinity points at it (:func:`dope_hope.maps.decode.corner_candidates`) and
   :func:`dope_hope.inference.pose_search.solve_pnp_candidates` finds the pose that explains most of
   them (:func:`dope_hope.inference.pose_search.solve_pnp_instances`: the peaks an accepted pose holds
   are no candidates of the centroids searched after it); two centroids explaining the same
   peaks give one detection, the higher-scoring. A centroid whose candidates allow no pose of
   ``min_score`` (:func:`dope_hope.maps.decode.keypoint_score_bound`: the mean of its
   ``pnp.min_points`` best keypoint types) is left out before the search: it costs no search
   and holds no peaks; the search, given ``min_score``, skips the minimal sets and the final
   PnP of a centroid whose poses could not reach it with the inliers they need
   (:func:`dope_hope.inference.pnp.least_score_divisor`).
   ``pose_search="groups"``: DOPE's decoding, one corner per type and centroid
   (:func:`dope_hope.maps.decode.decode_maps`), then :func:`dope_hope.inference.pnp.solve_pnp`.
   The cuboid is the object's: the model's size (mesh frame) or, with ``mesh=``, the
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
   biases the distance: pass the mesh for non-box objects). Where the search over
   ``line_search.search`` (0.8-1.25x the distance) finds its optimum on the bound, a second one
   over ``line_search.wide_search`` (0.5-2x) moves the pose, unless the depth already confirms
   the keypoints' pose (:func:`dope_hope.refine.icp.own_depth_support`: the object is then
   occluded, not misplaced; a box hidden behind a board is not moved onto the board). The
   keypoints of a small object put it 20-60 % too far or too near as often as not (the 4.5-cm
   lemon of ``bench/multi_object.py`` spans ~5 cells of a lite model's maps at 0.6 m).
6. **Depth ICP** (optional, ``icp=True``, :func:`dope_hope.refine.icp.icp_refine`): after the
   line search, point-to-plane ICP of ``icp_points`` model points against the depth under the
   object refines all six DoF; kept only when it does not fit the depth worse and keeps to the
   object's own depth support (the detected region: the silhouette of the pose it starts
   from). Without ``mesh=`` only the catalog's boxes are allowed; ``icp="auto"`` runs it where
   the image has depth and the object a surface to fit (:meth:`DopePredictor.icp_runs`).
7. **Turns by the texture** (optional, ``appearance.trained_turns``, where ICP does not run;
   :class:`dope_hope.inference.turns.TrainedTurns`): each pose turned about its object's long
   axis to the turn whose textured render the network's first layers find most like the image;
   before -LS, which then places the pose kept.

Several working sizes (optional, ``multiscale.scales``, :mod:`dope_hope.inference.scales`):
steps 1-4 at each (after the first only where its detections leave belief unexplained, with
``multiscale.gate``), the detections pooled (a duplicate of a higher-scoring one by its 2D box
dropped), then steps 5-7 on those kept.
"""
from __future__ import annotations

import functools
import math
import os
import warnings
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from dope_hope.assets import PRETRAINED_WEIGHTS
from dope_hope.errors import ConfigError, ModelFileError
from dope_hope.geometry import (
    LEGACY_KEYPOINT_ORDER,
    NUM_KEYPOINTS,
    legacy_keypoints_to_current,
    legacy_rotation_to_mesh,
    project_points,
    project_points_poses,
    projected_bbox,
    projected_bboxes,
    value_for_object,
)
from dope_hope.inference.backends import MapBackend, backend_objects, model_min_score, open_backend, start_backend
from dope_hope.inference.depth_confirm import keep_detection, pose_floor, worth_icp
from dope_hope.inference.detection import Detection
from dope_hope.inference.object_geometry import ObjectGeometry
from dope_hope.inference.options import InferenceOptions
from dope_hope.inference.pnp import PoseEstimate, pose_may_reach, score_in_view, solve_pnp
from dope_hope.inference.pose_search import solve_pnp_instances
from dope_hope.inference.reported_objects import meshes_by_group, select_groups
from dope_hope.inference.scales import belief_beyond_boxes, pool_detections, scaled_height
from dope_hope.inference.turns import TrainedTurns
from dope_hope.maps.decode import (
    corner_candidates,
    decode_maps,
    decoder_peaks,
)
from dope_hope.maps.peaks import Peaks, split_peaks
from dope_hope.preprocess import (
    NetworkInput,
    check_intrinsics,
    prepare_input,
    to_rgb8,
    working_size,
)
from dope_hope.refine.depth import DepthImage
from dope_hope.refine.icp import icp_refine, own_depth_support
from dope_hope.refine.line_search import depth_line_search

#: ``icp_reason`` of a detection that ``icp: auto`` leaves to -LS: its object has nothing to fit.
NO_ICP_SURFACE = "no surface to fit (icp: auto needs the object's mesh or a catalog box)"


# ----------------------------------------------------------------------------- predictor
class DopePredictor:
    """A network for one or more objects and everything to turn images into :class:`Detection` s.

    Args:
        weights: a dope-hope checkpoint (``.pth``/``.pt``), an exported ``.onnx`` model, or a
            ready :class:`MapBackend` instance.
        backend: "auto" (ONNX for ``.onnx``, else torch), "torch" or "onnx".
        device: torch device, or "cuda..." to ask onnxruntime for its CUDA provider.
        threads: CPU threads (torch.set_num_threads / onnxruntime intra-op threads).
        mesh: optional mesh of the object: a file (or loaded ``trimesh.Trimesh`` in metres)
            when the predictor reports one object, or a mapping class name -> mesh for any
            number (objects left out keep the model's cuboid). A mesh's box replaces the
            model's cuboid and its surface feeds the depth steps.
        mesh_units: units of the mesh files ("m", "cm", "mm"; default by suffix), or a mapping
            class name -> unit ("" for the others: objects of mixed units).
        options: :class:`~dope_hope.inference.options.InferenceOptions`, or a mapping of
            overrides of the packaged defaults (``dope_hope/configs/infer.yaml``).
        classes: report only these of the model's objects (names, case-insensitive; default
            all); ConfigError naming the model's objects for a class it does not detect.
        **overrides: single options on top (``height=400``, ``icp=True``, ``pnp={...}``, ...);
            an unknown name is a ConfigError.

    ``min_score``: when neither ``options`` nor ``overrides`` gives one, each object's own
    threshold when the model file records one (``ObjectInfo.min_score``: `dope-hope calibrate`),
    else the model's (``ModelInfo.min_score``), else the packaged default; given, it holds for
    every object. ``ObjectGeometry.min_score`` is the one each object uses.

    Attributes: backend, options, objects (one :class:`ObjectGeometry` per reported object,
    channel order), own_min_score, class_names, legacy, mean, std, stride. A predictor of one object also
    offers that object's class_name, cuboid_size_m, cuboid_center_m, mesh, cuboid_mesh,
    cuboid_pnp, model_points, bbox_points and icp_model.
    """

    def __init__(self, weights: str | os.PathLike | MapBackend, backend: str = "auto", device: str = "cpu",
                 threads: int | None = None, mesh: Any = None, mesh_units: str | Mapping[str, str] | None = None,
                 options: InferenceOptions | Mapping[str, Any] | None = None, classes: Sequence[str] | None = None,
                 **overrides: Any):
        given = {**(options.to_dict() if isinstance(options, InferenceOptions) else options or {}), **overrides}
        # built once (a bad option refused before a model loads); an InferenceOptions gives every option
        built = options if isinstance(options, InferenceOptions) and not overrides else InferenceOptions.from_mapping(given)
        if isinstance(classes, str):
            classes = [classes]
        if isinstance(weights, (str, os.PathLike)):
            self.backend: MapBackend = open_backend(weights, backend, device, threads)
        elif hasattr(weights, "run") and hasattr(weights, "stride"):
            self.backend = weights
        else:
            raise ConfigError(f"weights must be a file path or a MapBackend, got {type(weights).__name__}")
        b = self.backend
        own = model_min_score(b)  # the model's threshold, recorded with its weights: min_score unless given
        self.options = built if "min_score" in given or own is None else replace(built, min_score=own)
        fixed = getattr(b, "fixed_input_hw", None)
        if fixed is not None and len(self.options.multiscale.scales) > 1:
            raise ConfigError(f"multiscale.scales: this model takes {fixed[0]}x{fixed[1]} inputs only (a fixed-size "
                              "export), so it runs at one size: give one scale, or the checkpoint")
        self.legacy = b.frame == "legacy" or b.keypoint_order == LEGACY_KEYPOINT_ORDER
        self.mean = tuple(float(v) for v in b.mean)
        self.std = tuple(float(v) for v in b.std)
        self.stride = int(b.stride)
        model_objects = backend_objects(b)
        #: number of objects (channel groups) in the model's maps
        self.num_model_objects = len(model_objects)
        groups = select_groups(model_objects, classes)
        meshes = meshes_by_group(mesh, [model_objects[k].class_name for k in groups])
        self.objects = [ObjectGeometry(model_objects[k], k, self.legacy, meshes.get(i),
                                       value_for_object(mesh_units, model_objects[k].class_name),
                                       self.options.ls_points, self.options.icp_points)
                        for i, k in enumerate(groups)]
        for obj, k in zip(self.objects, groups):  # an explicit min_score, else the object's own
            own = model_objects[k].min_score
            obj.min_score = self.options.min_score if "min_score" in given or own is None else float(own)
        #: whether the thresholds are the model's own (recorded with its weights, none given)
        self.own_min_score = "min_score" not in given and (
            model_min_score(b) is not None or any(model_objects[k].min_score is not None for k in groups))
        #: the objects ICP may fit: all with icp=True (checked), those with a surface with "auto"
        self.icp_objects = {o.class_name for o in self.objects if self.options.icp is True or o.has_icp_surface()}
        if self.options.icp is True:
            for obj in self.objects:
                obj.check_icp_surface()
        self._turns: TrainedTurns | None = None  # appearance.trained_turns, built on first use
        self._turns_told = False  # whether the warning of trained_turns was issued

    # ------------------------------------------------------------------ one-object view
    @property
    def class_names(self) -> tuple[str, ...]:
        """The reported objects' classes, channel order."""
        return tuple(o.class_name for o in self.objects)

    def _only(self) -> ObjectGeometry:
        if len(self.objects) != 1:
            raise AttributeError(f"this predictor reports {len(self.objects)} objects ({', '.join(self.class_names)}): use .objects")
        return self.objects[0]

    class_name = property(lambda self: self._only().class_name, doc="The one object's class.")
    cuboid_size_m = property(lambda self: self._only().cuboid_size_m, doc="(3,) its box, mesh frame, m.")
    cuboid_center_m = property(lambda self: self._only().cuboid_center_m, doc="(3,) its box centre, m.")
    mesh = property(lambda self: self._only().mesh, doc="Its mesh or None.")
    cuboid_mesh = property(lambda self: self._only().cuboid_mesh, doc="(9, 3) mesh-frame keypoints.")
    cuboid_pnp = property(lambda self: self._only().cuboid_pnp, doc="(9, 3) keypoints PnP fits.")
    model_points = property(lambda self: self._only().model_points, doc="Line-search surface points.")
    bbox_points = property(lambda self: self._only().bbox_points, doc="Points bounding its projection.")
    icp_model = property(lambda self: self._only().icp_model, doc="ICP surface points and normals.")

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
        """Run the network: (belief (9K, h, w), affinity (16K, h, w), the NetworkInput) for
        the model's K objects (all of them, whatever ``classes`` keeps)."""
        net_in = image if isinstance(image, NetworkInput) else self.prepare(image)
        belief, affinity = self.backend.run(net_in.batch)
        belief, affinity = np.asarray(belief)[0], np.asarray(affinity)[0]
        Hp, Wp = net_in.batch.shape[2:]
        n = self.num_model_objects
        if belief.shape != (NUM_KEYPOINTS * n, Hp // self.stride, Wp // self.stride) or \
                affinity.shape != (2 * (NUM_KEYPOINTS - 1) * n,) + belief.shape[1:]:
            raise ModelFileError(getattr(self.backend, "source", "<model>"),
                                 f"network returned maps {belief.shape} / {affinity.shape} for an "
                                 f"input of {Hp}x{Wp} at stride {self.stride} ({n} object(s))")
        return belief, affinity, net_in

    def predict(self, image: np.ndarray, K: np.ndarray, depth: np.ndarray | DepthImage | None = None,
                depth_scale_m: float = 0.001, calibration: float = 1.0) -> list[Detection]:
        """Detect this predictor's objects in one image (one forward pass for all of them).

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
            Detections of every reported object, sorted by decreasing score, mesh-frame poses.
        """
        K = check_intrinsics(K)
        rgb = to_rgb8(image)
        depth = as_depth_image(depth, K, depth_scale_m, calibration, rgb.shape[:2])
        out = self.detect_image(rgb, K, depth)
        out.sort(key=lambda d: -d.score)
        return out

    def detect_image(self, rgb: np.ndarray, K: np.ndarray, depth: DepthImage | None,
                     cache: dict[tuple, Any] | None = None,
                     on_maps: Callable[[DopePredictor, np.ndarray, np.ndarray, NetworkInput], None] | None = None,
                     classes: Collection[str] | None = None) -> list[Detection]:
        """One image's detections (:func:`predict_many`'s step per predictor): for each working
        size (``multiscale.scales``; one by default) the network input from ``cache`` (filled
        when missing, shared by predictors of equal input; a subclass may keep more there, as
        the new objects of one start keep its maps), the maps (those of the first size passed
        to ``on_maps``), then :meth:`detections_from_maps`; several sizes' detections pooled
        (:func:`~dope_hope.inference.scales.pool_detections`), and then, where sizes were pooled
        or the turns run, the turns and the depth stages of those kept.
        ``rgb`` (H, W, 3) uint8, ``K`` checked intrinsics, ``depth`` a DepthImage or None."""
        cache = {} if cache is None else cache
        scales = self.options.multiscale.scales
        turns = self.trained_turns()
        late = turns is not None or len(scales) > 1  # the depth stages after the turns / the pooling
        out: list[Detection] = []
        floors = {o.class_name: pose_floor(o.min_score, self.options.depth_confirm, self.icp_runs(o, depth))
                  for o in self.objects}
        for i, (_, net_input) in enumerate(self.network_inputs(rgb, cache)):
            belief, affinity, net_in = self.infer_maps(net_input)
            if on_maps is not None and i == 0:
                on_maps(self, belief, affinity, net_in)
            out += self.detections_from_maps(belief, affinity, net_in, K, None if late else depth, classes, floors)
            if i == 0 and len(scales) > 1 and self.first_size_explains(belief, affinity, net_in, out, classes):
                break  # multiscale.gate: nothing the first size missed, no other size
        if not late:
            return out
        if len(scales) > 1:
            out = pool_detections(out, self.options.multiscale.duplicate_iou)
        for det in out:  # the turn first: -LS then places the pose it kept
            obj = self.object_of(det)
            if turns is not None and not self.icp_runs(obj, depth):
                turns.turn(det, rgb, K)
            self.depth_stages(obj, det, depth)
            self.project_detection(obj, det, K, rgb.shape[:2])
        return [d for d in out if keep_detection(d, self.object_of(d).min_score, self.options.depth_confirm)]

    def first_size_explains(self, belief: np.ndarray, affinity: np.ndarray, net_in: NetworkInput,
                            detections: Sequence[Detection], classes: Collection[str] | None = None) -> bool:
        """Whether the first working size's ``detections`` explain its maps, so that the other
        sizes need not run (``multiscale.gate``, :mod:`~dope_hope.inference.scales`): no object's
        belief outside its detections' 2D boxes (at its threshold) reaches the gate. False without a gate."""
        gate = self.options.multiscale.gate
        if gate is None:
            return False
        for obj in self.objects:
            if classes is None or obj.class_name in classes:
                boxes = [net_in.to_network_px(np.reshape(d.bbox_2d, (2, 2))) / self.stride for d in detections
                         if d.class_name == obj.class_name and d.bbox_2d is not None and d.score >= obj.min_score]
                if belief_beyond_boxes(obj.channels(belief, affinity)[0], boxes) > gate:
                    return False
        return True

    def network_inputs(self, rgb: np.ndarray, cache: dict[tuple, Any], scales: Sequence[float] | None = None,
                       ) -> list[tuple[tuple, NetworkInput]]:
        """(cache key, :class:`NetworkInput`) of the (H, W, 3) uint8 image at each of
        :meth:`scale_sizes`, from ``cache`` (filled where missing: predictors of equal working
        size and normalization share an input)."""
        out = []
        for resized, padded in self.scale_sizes(rgb.shape[:2], scales):
            key = (resized, padded, self.mean, self.std)
            if key not in cache:
                cache[key] = prepare_input(rgb, resized, self.mean, self.std, padded)
            out.append((key, cache[key]))
        return out

    def scale_sizes(self, image_hw: tuple[int, int], scales: Sequence[float] | None = None,
                    ) -> list[tuple[tuple[int, int], tuple[int, int]]]:
        """((H', W') resized content, (Hp, Wp) padded network input) of each of ``scales``
        (default ``multiscale.scales``) for an image of (H, W): scale 1 is :meth:`working_size`,
        another that size's height times the scale."""
        base, key = self.working_size(image_hw), "multiscale.scales" if scales is None else "new_object.scales"
        return [base if s == 1.0 else working_size(image_hw, height=scaled_height(base[0][0], s), too_large=(
            f"{key} holds {s:g} (times the working height of {base[0][0]} px): give a smaller scale"))
                for s in (self.options.multiscale.scales if scales is None else scales)]

    def trained_turns(self) -> TrainedTurns | None:
        """The turns of ``appearance.trained_turns`` (module docstring, step 7), built on first
        use, the objects they skip named in a warning; None where the setting is off, or where
        ICP runs on every detection (``icp=True``; a warning says so, once). Their features: the backend's own first layers (a
        PyTorch model), else the shipped start's (an ONNX model)."""
        if not self.options.appearance.trained_turns:
            return None
        told, self._turns_told = self._turns_told, True
        if self.options.icp is True:
            if not told:
                warnings.warn("appearance.trained_turns does not run with ICP: the depth fit places the turn",
                              UserWarning, stacklevel=3)
            return None
        if self._turns is None:
            features = getattr(self.backend, "texture_features", None) or _shipped_start_features()
            self._turns = TrainedTurns(self.objects, self.options.appearance, features)
            if self._turns.skipped and not told:
                warnings.warn("appearance.trained_turns: no turns for " + "; ".join(
                    f"{name} ({why})" for name, why in self._turns.skipped.items()), UserWarning, stacklevel=3)
        return self._turns

    def close(self) -> None:
        """Free the GL contexts of ``appearance.trained_turns`` (a later image builds them again)."""
        if self._turns is not None:
            self._turns.close()
            self._turns = None

    def detections_from_maps(self, belief: np.ndarray, affinity: np.ndarray, net_in: NetworkInput,
                             K: np.ndarray, depth: DepthImage | None = None,
                             classes: Collection[str] | None = None,
                             floors: Mapping[str, float] | None = None) -> list[Detection]:
        """Decode + PnP (+ line search, ICP) the maps of :meth:`infer_maps` (see :meth:`predict`),
        object by object; an object whose belief maps peak nowhere above the decode threshold
        is skipped before any decoding (one max over its maps), and so is one whose peaks could
        give no pose the score ``min_score`` asks (:func:`~dope_hope.inference.pnp.pose_may_reach` of all its peaks:
        the weak maps of an absent object cost one peak search, not a pose search). The peaks of
        all the objects left are found in one search over their stacked belief maps (each
        channel on its own: the peaks of a search per object, for about the cost of one).
        ``classes``: decode only those of the predictor's objects this time (exact class names;
        None: all). ``floors``: the lowest pose score searched per class (default each object's
        threshold; lower where :mod:`~dope_hope.inference.depth_confirm` runs: the depth
        stages then keep or drop what scores under the threshold)."""
        K = check_intrinsics(K)
        K_net = net_in.network_K(K)
        threshold = self.options.decode.threshold
        live = []
        for obj in self.objects:
            if classes is not None and obj.class_name not in classes:
                continue
            b, a = obj.channels(belief, affinity)
            if b.max() > threshold:  # find_peaks keeps no cell whose belief is <= threshold
                live.append((obj, b, a))
        if not live:
            return []
        stacked = live[0][1] if len(live) == 1 else np.concatenate([b for _, b, _ in live])
        all_peaks = split_peaks(decoder_peaks(stacked, self.options.decode), len(live), NUM_KEYPOINTS)
        out: list[Detection] = []
        for (obj, b, a), peaks in zip(live, all_peaks):
            floor = obj.min_score if floors is None else floors[obj.class_name]
            if not pose_may_reach(peaks.channel, peaks.score, self.options.pnp, floor):
                continue  # no pose of these maps could reach the floor: nothing to decode
            out += self._object_detections(obj, b, a, peaks, net_in, K, K_net, depth, floor)
        out.sort(key=lambda d: -d.score)
        return out

    def _object_detections(self, obj: ObjectGeometry, belief: np.ndarray, affinity: np.ndarray, peaks: Peaks,
                           net_in: NetworkInput, K: np.ndarray, K_net: np.ndarray,
                           depth: DepthImage | None, floor: float) -> list[Detection]:
        """One object's detections from its own (9, h, w) / (16, h, w) maps and their peaks,
        its poses searched down to ``floor`` (those under its threshold kept only where the depth
        confirms them, :func:`~dope_hope.inference.depth_confirm.keep_detection`)."""
        mean_scale = math.sqrt(net_in.scale[0] * net_in.scale[1])
        out: list[Detection] = []
        pnp = self.options.pnp
        for est in self._poses(belief, affinity, K_net, obj.cuboid_pnp, floor, peaks):
            if pnp.score_in_view:  # a keypoint beyond the border is not a missing one
                est = replace(est, score=score_in_view(est, net_in.resized_hw, pnp.min_points))
            if est.score < floor:
                continue
            R, t = est.R, est.t
            kp, scores, inliers = est.keypoints, est.keypoint_scores, est.inliers
            if self.legacy:
                R = legacy_rotation_to_mesh(R)
                kp = legacy_keypoints_to_current(kp)
                scores = legacy_keypoints_to_current(scores[:, None])[:, 0]
                inliers = legacy_keypoints_to_current(inliers[:, None])[:, 0]
            elif obj.pnp_axes is not None:  # PnP in another frame of the box (ObjectGeometry.set_pnp_frame)
                R = R @ obj.pnp_axes
                kp, scores, inliers = kp[obj.pnp_order], scores[obj.pnp_order], inliers[obj.pnp_order]
            det = Detection(
                class_name=obj.class_name, score=float(est.score), R=R, t=t.copy(),
                keypoints_2d=net_in.to_original_px(kp), keypoint_scores=np.asarray(scores, float),
                inliers=np.asarray(inliers, bool), projected_2d=np.zeros((NUM_KEYPOINTS, 2)),
                reprojection_error_px=float(est.reprojection_error_px / mean_scale),
                cuboid_size_m=obj.cuboid_size_m.copy(), cuboid_center_m=obj.cuboid_center_m.copy(),
            )
            self.depth_stages(obj, det, depth)
            if depth is None or keep_detection(det, obj.min_score, self.options.depth_confirm):
                out.append(det)  # without depth here (several sizes, the turns), the caller's stages decide
        if out:  # the final poses' projections, all at once
            Rs, ts = np.stack([d.R for d in out]), np.stack([d.t for d in out])
            projected = project_points_poses(obj.cuboid_mesh, K, Rs, ts)
            boxes = projected_bboxes(obj.bbox_points, K, Rs, ts, net_in.original_hw)
            for det, uv, box in zip(out, projected, boxes):
                det.projected_2d, det.bbox_2d = uv, box
        return out

    def depth_stages(self, obj: ObjectGeometry, det: Detection, depth: DepthImage | None) -> None:
        """-LS, then ICP where it runs (:meth:`icp_runs`; under the threshold only after -LS,
        :func:`~dope_hope.inference.depth_confirm.worth_icp`), in place on ``det`` of object ``obj``
        (its pose the keypoints'); without ``depth`` only the reason ICP did not run (``projected_2d``, ``bbox_2d``: the caller's)."""
        if depth is not None:
            self._line_search(obj, det, depth)
            if self.icp_runs(obj, depth):
                if worth_icp(det, obj.min_score):
                    self._refine_icp(obj, det, depth)
            elif self.options.icp:  # (icp: auto, an object with no mesh and no catalog box)
                det.icp_reason = NO_ICP_SURFACE
        elif self.options.icp:
            det.icp_reason = "no depth image"

    def icp_runs(self, obj: ObjectGeometry, depth: DepthImage | None) -> bool:
        """Whether ICP refines object ``obj``'s detections in an image with ``depth`` (or None):
        ``icp`` true and depth, or "auto", depth and a surface to fit (:attr:`icp_objects`)."""
        return bool(self.options.icp) and depth is not None and obj.class_name in self.icp_objects

    def object_of(self, det: Detection) -> ObjectGeometry:
        """The reported object a detection of this predictor belongs to (by class)."""
        for obj in self.objects:
            if obj.class_name == det.class_name:
                return obj
        raise ConfigError(f"{det.class_name!r} is not an object of this predictor ({', '.join(self.class_names)})")

    def refine_icp(self, det: Detection, depth: DepthImage) -> Detection:
        """The ICP step of the module docstring on one detection, whatever ``icp`` was set to:
        a copy of ``det`` (as :meth:`predict` returns it with ``depth``, i.e. after the line
        search) refined by ICP against ``depth``; ``det`` itself is unchanged. Lets a caller
        keep both the -LS and the -LS + ICP pose without decoding the maps twice."""
        obj = self.object_of(det)
        out = replace(det)
        self._refine_icp(obj, out, depth)
        self.project_detection(obj, out, depth.K, depth.hw)
        return out

    @staticmethod
    def project_detection(obj: ObjectGeometry, det: Detection, K: np.ndarray, image_hw: tuple[int, int]) -> None:
        """``det.projected_2d`` and ``det.bbox_2d`` of its pose, in place: object ``obj``'s cuboid
        keypoints and 2D box (clipped to the (H, W) ``image_hw``) with intrinsics K (3, 3)."""
        det.projected_2d = project_points(obj.cuboid_mesh, K, det.R, det.t)
        det.bbox_2d = projected_bbox(obj.bbox_points, K, det.R, det.t, image_hw)

    def _line_search(self, obj: ObjectGeometry, det: Detection, depth: DepthImage) -> None:
        """The -LS step of the module docstring, in place on ``det`` (its pose the keypoints'):
        the line search over ``line_search.search``; where its optimum lies on the bound, once
        more over ``line_search.wide_search``, unless the depth already confirms the keypoints'
        pose (its own depth support, :func:`~dope_hope.refine.icp.own_depth_support` with the
        ``icp_refine`` settings of that rule, reaches ``min_own_support``: the object is
        occluded, not misplaced, and a wider search would move it onto its occluder)."""
        options = self.options
        settings = options.line_search
        ls = depth_line_search(det.R, det.t, obj.model_points, depth, settings)
        wide_range = settings.wide_search
        if ls.at_bound and wide_range is not None:
            label = f"search {wide_range[0]:g}-{wide_range[1]:g}"
            here = own_depth_support(det.R, det.t, obj.model_points, depth, options.icp_refine)
            if here >= options.icp_refine.min_own_support:
                ls = replace(ls, reason=f"{ls.reason}; no {label}: the depth confirms the keypoints' pose "
                                        f"(own depth support {here:.2f})")
            else:
                wide = depth_line_search(det.R, det.t, obj.model_points, depth, replace(settings, search=wide_range))
                ls = replace(wide, reason=f"ok ({label})") if wide.applied else \
                    replace(ls, reason=f"{ls.reason}; {label}: {wide.reason}")
        det.t, det.ls_applied, det.ls_reason, det.ls_scale = ls.t, ls.applied, ls.reason, ls.scale

    def _refine_icp(self, obj: ObjectGeometry, det: Detection, depth: DepthImage) -> None:
        """The ICP step of the module docstring, in place on ``det`` (after the line search)."""
        points, normals = obj.icp_model
        res = icp_refine(det.R, det.t, points, normals, depth, self.options.icp_refine)
        det.icp_applied, det.icp_reason = res.applied, res.reason
        det.icp_fit = res.fit_after if res.applied else res.fit_before
        if res.applied:
            det.R, det.t = res.R, res.t

    def _poses(self, belief: np.ndarray, affinity: np.ndarray, K_net: np.ndarray,
               cuboid: np.ndarray, min_score: float, peaks: Peaks | None = None) -> list[PoseEstimate]:
        """Network-image poses of the instances in one object's maps (step 3 of the module
        docstring), best first; keypoints in the network's own order; ``cuboid`` (9, 3);
        ``min_score``: the object's threshold; ``peaks``: the maps'
        :func:`~dope_hope.maps.decode.decoder_peaks` when already found."""
        options = self.options
        if options.pose_search == "groups":
            found = [solve_pnp(inst.keypoints, inst.scores, cuboid, K_net, options.pnp)
                     for inst in decode_maps(belief, affinity, self.stride, options.decode, peaks=peaks)]
            return [e for e in found if e is not None]
        candidates = corner_candidates(belief, affinity, self.stride, options.decode, peaks=peaks)
        # A centroid whose candidates allow no pose min_score keeps: no search.
        candidates = [c for c in candidates if pose_may_reach(c.keypoint_ids, c.scores, options.pnp, min_score)]
        return solve_pnp_instances([(c.keypoint_ids, c.xy, c.scores) for c in candidates], cuboid,
                                   K_net, options.hypotheses, options.pnp, min_score=min_score)

    def __repr__(self) -> str:
        return (f"DopePredictor(classes={list(self.class_names)!r}, stride={self.stride}, "
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
                 classes: Collection[str] | None = None) -> list[Detection]:
    """Run several predictors on one image; detections sorted by decreasing score.

    The image is converted once, and resized/normalized once per distinct working size and
    normalization (predictors with equal settings share the network input).
    ``on_maps(predictor, belief, affinity, network_input)`` is called with each model's maps
    (e.g. to draw them). ``classes``: decode only these objects (exact class names; a
    predictor with none of them is not run; None: every predictor's objects).
    """
    K = check_intrinsics(K)
    rgb = to_rgb8(image)
    depth = as_depth_image(depth, K, depth_scale_m, calibration, rgb.shape[:2])
    cache: dict[tuple, Any] = {}
    out: list[Detection] = []
    for p in predictors:
        if classes is not None and not set(p.class_names) & set(classes):
            continue
        out.extend(p.detect_image(rgb, K, depth, cache, on_maps, classes))
    out.sort(key=lambda d: -d.score)
    return out


@functools.cache
def _shipped_start_features() -> Callable[[np.ndarray], np.ndarray]:
    """The shipped pretrained start's first layers on the CPU (``TorchBackend.texture_features``),
    for a model whose backend cannot run its own (ONNX); loaded once."""
    return start_backend(PRETRAINED_WEIGHTS, "start", np.ones(3)).texture_features
