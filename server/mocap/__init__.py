"""Facial motion capture: marker takes in (C3D, TRC, CSV), cleaned, stabilised and retargeted onto a face.

After Sánchez Lorenzo (2006) ch. 4 and Kshirsagar et al. (head pose, mocap -> FAP).

Modules:
    io          read/write takes (C3D, TRC, CSV: the pure parsers in protocol.markers_file)
    layout      the marker layout JSON and marker placement on a face (vertex, FP, automatic)
    clean       spike rejection, DCT gap filling, constant-velocity Kalman filter, RTS smoother,
                low-rank projection of displacements (batch)
    stabilise   head pose (Kabsch / Kshirsagar's three markers), its smoothing, refinement with every
                marker (batch) and removal
    retarget    RBF map actor neutral -> face (inverse multiquadric or r, with an affine part)
    rig         per-take set-up shared by batch and live (placement, retarget, anchors, FAPs)
    prior       the face prior: the face's expression shapes (and mirrors) fitted to the markers,
                carried to every vertex by a per-vertex channel (``FaceState.shapes``;
                ``--prior auto``, the default, when the face has shapes)
    to_fap      projection of retargeted displacements to MPEG-4 FAPs
    driver      batch: ``load(path, face, layout=None, **options) -> Animation``
    live        ``MarkerLiveDriver(face, names, layout).push(xyz (M, 3), t) -> [FaceState]``
    generate    test takes with ground truth from the ICT FaceKit expressions (CLI)
    synthetic   synthetic takes on any face (tests, live benchmark)

Command lines:
    python -m facecast.server.mocap.generate --out DIR [--markers 60] [--seconds 10] [--fps 120]
    facecast render DIR/take.c3d --face <ICT mesh> -o out.glb|out.npz|out.fap   (DIR/take.layout.json: ICT vertices)
    facecast render DIR/take.c3d --layout DIR/take.layout-fp.json -o out.npz   (retarget onto the built-in head)
    python bench/mocap_cleaning.py | bench/mocap_fidelity.py | bench/mocap_live.py
"""
