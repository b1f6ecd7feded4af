//! Build script: make the binary find the OpenCV built by `scripts/setup` at run time (rpath), refuse to build
//! against an OpenCV without the contrib module `xfeatures2d` (the `opencv` crate would silently drop FREAK),
//! record the default ONNX Runtime library path of the setup prefix, check that the console's libraries are
//! installed (the binary embeds them), and generate the gRPC code.
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

    // The console's browser libraries (npm, ui/package-lock.json), embedded by src/server/http/ui.rs.
    println!("cargo:rerun-if-changed=ui/package-lock.json");
    if !PathBuf::from("ui/node_modules/three/build/three.module.js").is_file() {
        panic!(
            "ui/node_modules is missing: run `scripts/setup` once (it installs the console's libraries with \
             `npm ci --ignore-scripts` in ui/), or run that command yourself"
        );
    }

    // gRPC code and the descriptor set that server reflection serves; protoc comes from Debian's
    // protobuf-compiler (installed by scripts/setup).
    println!("cargo:rerun-if-changed=proto/scone/v1/scone.proto");
    let out = PathBuf::from(env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    tonic_prost_build::configure()
        .file_descriptor_set_path(out.join("scone_descriptor.bin"))
        .compile_protos(&["proto/scone/v1/scone.proto"], &["proto"])
        .unwrap_or_else(|e| panic!("compiling proto/scone/v1/scone.proto (is protoc installed?): {e}"));
}
