# shellcheck shell=bash
# Sourced by the project's scripts: where the built dependencies live and how cargo finds them.
# Everything heavy (OpenCV build, ONNX Runtime library, Python virtualenvs) sits in a prefix outside
# the clone, so a fresh clone reuses it. Override with SCONE_PREFIX.
SCONE_PREFIX="${SCONE_PREFIX:-$HOME/.cache/scone}"
SCONE_OPENCV_VERSION="${SCONE_OPENCV_VERSION:-4.12.0.88}"
SCONE_ORT_VERSION="${SCONE_ORT_VERSION:-1.31.1}"
SCONE_OPENCV_PREFIX="$SCONE_PREFIX/opencv-$SCONE_OPENCV_VERSION"
SCONE_ORT_DIR="$SCONE_PREFIX/onnxruntime-$SCONE_ORT_VERSION"
export SCONE_PREFIX SCONE_OPENCV_PREFIX SCONE_ORT_DIR
export SCONE_ORT_LIB="$SCONE_ORT_DIR/lib/libonnxruntime.so"
export PKG_CONFIG_PATH="$SCONE_OPENCV_PREFIX/lib/pkgconfig${PKG_CONFIG_PATH:+:$PKG_CONFIG_PATH}"
export OPENCV_INCLUDE_PATHS="$SCONE_OPENCV_PREFIX/include/opencv4"
export OPENCV_LINK_PATHS="$SCONE_OPENCV_PREFIX/lib"
export OPENCV_LINK_LIBS="opencv_xfeatures2d,opencv_calib3d,opencv_features2d,opencv_flann,opencv_imgcodecs,opencv_imgproc,opencv_core"
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$SCONE_PREFIX/target}"
