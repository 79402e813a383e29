//! Writes the Sobol byte tables `sampler::sobol_4d` reads (`$OUT_DIR/sobol_byte_tables.rs`), worked
//! out here by `sobol_burley` itself so that the render loop reads a plain static: a lazily
//! built table costs a check of its initialisation on every read (1 % of a Cornell-box render's
//! instructions under callgrind, `std::sync::once`).

use std::fmt::Write;

fn main() {
    let mut out = String::from("/// Sobol dimensions 0–3 of each value of the reversed index's bits 16–23 (`[0]`) and 24–31\n/// (`[1]`): `sobol_burley::parts::sobol_int4_rev(b << 16 or b << 24, 0)`, from `build.rs`.\nstatic SOBOL_BYTE_TABLES: [[[u32; 4]; 256]; 2] = [\n");
    for shift in [16u32, 24] {
        out.push_str("    [\n");
        for b in 0..256u32 {
            let v: [u32; 4] = sobol_burley::parts::sobol_int4_rev(b << shift, 0).into();
            writeln!(out, "        [{:#010x}, {:#010x}, {:#010x}, {:#010x}],", v[0], v[1], v[2], v[3])
                .expect("writing to a String");
        }
        out.push_str("    ],\n");
    }
    out.push_str("];\n");
    let dir = std::env::var("OUT_DIR").expect("cargo sets OUT_DIR for build scripts");
    std::fs::write(std::path::Path::new(&dir).join("sobol_byte_tables.rs"), out).expect("writing the Sobol tables");
    println!("cargo::rerun-if-changed=build.rs");
}
