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
