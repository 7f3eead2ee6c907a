"""The SMPL 22-joint body and the 16 MoCap-style landmarks (docs/protocol.md, conventions)."""

JOINT_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee",
    "spine2", "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot",
    "neck", "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist",
)
PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)
NUM_JOINTS = len(JOINT_NAMES)
JOINT_INDEX = {name: i for i, name in enumerate(JOINT_NAMES)}

# 16 MoCap-style markers, each tied to one template vertex of a body model.
LANDMARK_NAMES = (
    "head", "sternum", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist", "pelvis_front", "pelvis_back", "left_knee", "right_knee",
    "left_ankle", "right_ankle", "left_toe", "right_toe",
)
NUM_LANDMARKS = len(LANDMARK_NAMES)

# Left/right mirror of the joints (index -> index), for symmetric augmentation.
MIRROR = tuple(
    JOINT_INDEX[n.replace("left_", "@").replace("right_", "left_").replace("@", "right_")]
    for n in JOINT_NAMES
)

# An SMPL-like neutral rest skeleton (metres; y up, facing +z, left at +x; pelvis at the origin),
# rounded values of the typical SMPL neutral T-pose joint layout. Used only when the embedded Anny
# body cannot be built, as the fixed skeleton of a training loss (priors.training.fixed_rest_skeleton),
# and by priors whose paper size assumes an SMPL skeleton; it is not a body model.
SMPL_LIKE_REST_JOINTS = (
    (0.000, 0.000, 0.000),  # pelvis
    (0.070, -0.090, -0.005),  # left_hip
    (-0.068, -0.090, -0.006),  # right_hip
    (0.000, 0.110, -0.025),  # spine1
    (0.105, -0.475, 0.010),  # left_knee
    (-0.105, -0.475, 0.010),  # right_knee
    (0.000, 0.245, -0.020),  # spine2
    (0.090, -0.880, -0.045),  # left_ankle
    (-0.090, -0.880, -0.045),  # right_ankle
    (0.000, 0.300, 0.005),  # spine3
    (0.115, -0.940, 0.075),  # left_foot
    (-0.115, -0.940, 0.075),  # right_foot
    (0.000, 0.510, -0.035),  # neck
    (0.075, 0.420, -0.020),  # left_collar
    (-0.075, 0.420, -0.020),  # right_collar
    (0.000, 0.580, 0.015),  # head
    (0.170, 0.450, -0.030),  # left_shoulder
    (-0.170, 0.450, -0.030),  # right_shoulder
    (0.425, 0.440, -0.050),  # left_elbow
    (-0.425, 0.440, -0.050),  # right_elbow
    (0.680, 0.445, -0.050),  # left_wrist
    (-0.680, 0.445, -0.050),  # right_wrist
)
