//! The EXR reader on arbitrary bytes: an image or an error, never a panic or an abort (a failed
//! allocation aborts, so sizes must be bounded before the decoder allocates).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = renderer::image_io::read_exr_bytes(data);
});
