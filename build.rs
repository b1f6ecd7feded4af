//! Build script: make the binary find the OpenCV built by `scripts/setup` at run time (rpath), refuse to build
//! against an OpenCV without the contrib module `xfeatures2d` (the `opencv` crate would silently drop FREAK),
//! and record the default ONNX Runtime library path of the setup prefix.
use std::env;
use std::path::PathBuf;

fn main() {
    for var in ["OPENCV_INCLUDE_PATHS", "OPENCV_LINK_PATHS", "SCONE_PREFIX", "SCONE_ORT_LIB"] {
        println!("cargo:rerun-if-env-changed={var}");
    }
    let include = env::var("OPENCV_INCLUDE_PATHS").unwrap_or_default();
    let link = env::var("OPENCV_LINK_PATHS").unwrap_or_default();
    if include.is_empty() || link.is_empty() {
        panic!(
            "OPENCV_INCLUDE_PATHS / OPENCV_LINK_PATHS are not set: run `scripts/setup` once (it builds OpenCV with \
             xfeatures2d and writes .cargo/config.toml), or `source scripts/env.sh` before cargo"
        );
    }
    let has_xfeatures2d =
        include.split(',').map(|p| PathBuf::from(p.trim()).join("opencv2/xfeatures2d.hpp")).any(|p| p.is_file());
    if !has_xfeatures2d {
        panic!(
            "no opencv2/xfeatures2d.hpp under OPENCV_INCLUDE_PATHS={include}: scone needs OpenCV built with the \
             contrib module xfeatures2d (FREAK, matchGMS); run `scripts/setup`"
        );
    }
    for dir in link.split(',').map(str::trim).filter(|d| !d.is_empty()) {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}");
    }
    let ort = env::var("SCONE_ORT_LIB").unwrap_or_default();
    println!("cargo:rustc-env=SCONE_DEFAULT_ORT_LIB={ort}");
}
