//! Compiles the .proto files with protox (pure Rust: no protoc on the machine) and prost-build.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let files = ["emr/v1/messages.proto"];
    for f in files {
        println!("cargo:rerun-if-changed={f}");
    }
    let descriptors = protox::compile(files, ["."])?;
    prost_build::Config::new().bytes(["."]).compile_fds(descriptors)?;
    Ok(())
}
