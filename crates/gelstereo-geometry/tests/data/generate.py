#!/usr/bin/python3
"""Regenerates the calibration and triangulation fixtures of gelstereo-geometry's tests.

Run with Debian's Python (it has python3-opencv 4.6 and python3-mrcal 2.2):

    apt-get install -y python3-mrcal mrcal python3-opencv
    cd crates/gelstereo-geometry/tests/data && /usr/bin/python3 generate.py

Everything is written by the reference tools themselves (cv2.FileStorage, mrcal.cameramodel.write,
mrcal.triangulate), so the Rust readers are tested against files they did not write. The rig is
the reference sensor's (calib/reference-sensor.json): two 640x480 cameras 24 mm behind the gel,
10 mm apart, converging on the gel centre. Deterministic (seeded).
"""
import cv2
import mrcal
import numpy as np

W, H = 640, 480
K1 = np.array([[520.0, 0, 321.3], [0, 521.5, 238.4], [0, 0, 1]])
K2 = np.array([[518.6, 0, 318.2], [0, 519.8, 241.1], [0, 0, 1]])
D8_1 = np.array([-0.065, 0.021, 0.0004, -0.0003, -0.004, 0.002, -0.001, 0.0005])
D8_2 = np.array([-0.059, 0.018, -0.0002, 0.0005, -0.003, 0.001, 0.0007, -0.0004])
D12_1 = np.concatenate([D8_1, [0.0011, -0.0004, 0.0008, 0.0002]])
D12_2 = np.concatenate([D8_2, [-0.0006, 0.0003, -0.0009, 0.0001]])


def look_at(position, target=(0.0, 0.0, 0.0), up=(0.0, -1.0, 0.0)):
    """world_from_cam rotation for a camera at `position` looking at `target` (y down)."""
    z = np.asarray(target, float) - np.asarray(position, float)
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def rig_extrinsics():
    c1, c2 = np.array([-5.0, 0.0, -24.0]), np.array([5.0, 0.05, -24.0])
    R_w1, R_w2 = look_at(c1), look_at(c2)
    # p_in_right = R * p_in_left + T
    R = R_w2.T @ R_w1
    T = R_w2.T @ (c1 - c2)
    return R, T.reshape(3, 1)


R, T = rig_extrinsics()


def write_fs(path, names, D1, D2, size_keys=True, fmt=None):
    fs = cv2.FileStorage(path, cv2.FILE_STORAGE_WRITE)
    fs.write(names[0], K1)
    fs.write("D1", D1.reshape(1, -1))
    fs.write(names[1], K2)
    fs.write("D2", D2.reshape(1, -1))
    fs.write("R", R)
    fs.write("T", T)
    if size_keys:
        fs.write("image_width", W)
        fs.write("image_height", H)
    fs.release()


# Accepted OpenCV files.
write_fs("opencv8.yaml", ("K1", "K2"), D8_1, D8_2)
write_fs("opencv5.xml", ("K1", "K2"), D8_1[:5], D8_2[:5])
write_fs("stereo_calib_m1m2.yml", ("M1", "M2"), D12_1, D12_2)

# The two files OpenCV's samples/cpp/stereo_calib.cpp writes, with its key names (no image size).
fs = cv2.FileStorage("stereo_calib_intrinsics.yml", cv2.FILE_STORAGE_WRITE)
for key, value in [("M1", K1), ("D1", D8_1[:5].reshape(1, -1)), ("M2", K2), ("D2", D8_2[:5].reshape(1, -1))]:
    fs.write(key, value)
fs.release()
R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(K1, D8_1[:5], K2, D8_2[:5], (W, H), R, T, alpha=-1)
fs = cv2.FileStorage("stereo_calib_extrinsics.yml", cv2.FILE_STORAGE_WRITE)
for key, value in [("R", R), ("T", T), ("R1", R1), ("R2", R2), ("P1", P1), ("P2", P2), ("Q", Q)]:
    fs.write(key, value)
fs.release()


def model(lensmodel, K, D, rt):
    intr = np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], D])
    return mrcal.cameramodel(intrinsics=(lensmodel, intr), imagersize=(W, H), extrinsics_rt_fromref=rt)


rt_right = np.concatenate([cv2.Rodrigues(R)[0].ravel(), T.ravel()])
zero = np.zeros(6)
for name, lens, d1, d2 in [
    ("opencv8", "LENSMODEL_OPENCV8", D8_1, D8_2),
    ("opencv12", "LENSMODEL_OPENCV12", D12_1, D12_2),
    ("opencv5", "LENSMODEL_OPENCV5", D8_1[:5], D8_2[:5]),
    ("opencv4", "LENSMODEL_OPENCV4", D8_1[:4], D8_2[:4]),
    ("pinhole", "LENSMODEL_PINHOLE", D8_1[:0], D8_2[:0]),
]:
    model(lens, K1, d1, zero).write(f"{name}_left.cameramodel")
    model(lens, K2, d2, rt_right).write(f"{name}_right.cameramodel")

# Rejected by name: lens models gelstereo does not implement, written by mrcal.
mrcal.cameramodel(
    intrinsics=("LENSMODEL_CAHVOR", np.array([520.0, 521.5, 321.3, 238.4, 0.01, 0.02, 0.1, 0.2, 0.3])),
    imagersize=(W, H),
).write("rejected_cahvor.cameramodel")
mrcal.cameramodel(
    intrinsics=("LENSMODEL_OPENCV8", np.concatenate([[520.0, 521.5, 321.3, 238.4], D8_1])),
    imagersize=(W, H),
).write("opencv8_at_ref.cameramodel")

# Triangulation reference: points on and around the gel, projected with OpenCV, with 0.3 px of noise
# so the methods disagree, triangulated by mrcal (Lee-Civera mid2 and Lindstrom) from the OPENCV8
# pair. Columns: x_left,y_left,x_right,y_right,X_true,Y_true,Z_true,X_mid2,Y_mid2,Z_mid2,X_lind,Y_lind,Z_lind
rng = np.random.default_rng(6)
n = 200
P = np.column_stack([rng.uniform(-8, 8, n), rng.uniform(-8, 8, n), rng.uniform(-1.5, 2.5, n)])
R_w1 = look_at([-5.0, 0.0, -24.0])
p_left = (P - np.array([-5.0, 0.0, -24.0])) @ R_w1  # world -> left camera
ql = cv2.projectPoints(p_left, np.zeros(3), np.zeros(3), K1, D8_1)[0].reshape(-1, 2)
qr = cv2.projectPoints(p_left, cv2.Rodrigues(R)[0], T, K2, D8_2)[0].reshape(-1, 2)
ql += rng.normal(0, 0.3, ql.shape)
qr += rng.normal(0, 0.3, qr.shape)
models = [mrcal.cameramodel("opencv8_left.cameramodel"), mrcal.cameramodel("opencv8_right.cameramodel")]
q = np.stack([ql, qr], axis=1)
mid2 = mrcal.triangulate(q, models, method=mrcal.triangulate_leecivera_mid2)
lind = mrcal.triangulate(q, models, method=mrcal.triangulate_lindstrom)
np.savetxt(
    "triangulation_mrcal.csv",
    np.column_stack([ql, qr, p_left, mid2, lind]),
    delimiter=",",
    fmt="%.17g",
    header="x_left,y_left,x_right,y_right,X_true,Y_true,Z_true,X_mid2,Y_mid2,Z_mid2,X_lind,Y_lind,Z_lind",
    comments="",
)
print("ok")
