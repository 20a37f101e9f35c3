//! Fuzz target: arbitrary bytes into both decoders, in arbitrary chunks. No input may panic,
//! and every packet that decodes must re-encode to a frame that decodes to the same packet.
//! Run with `cargo +nightly fuzz run decode` from `firmware-protocol/`.
#![no_main]

use libfuzzer_sys::fuzz_target;
use polar_firmware_protocol::{encode_vec, Command, Decoder, Message, Packet, Reply};

fn check<M: Message + PartialEq + core::fmt::Debug + Copy>(data: &[u8]) {
    let mut d = Decoder::<M>::new();
    for &b in data {
        if let Some(Ok(p)) = d.feed(b) {
            let wire = encode_vec(p.seq, &p.message);
            let mut again = Decoder::<M>::new();
            let back: Vec<_> = wire.iter().filter_map(|&b| again.feed(b)).collect();
            assert_eq!(back, vec![Ok(Packet { seq: p.seq, message: p.message })]);
        }
    }
}

fuzz_target!(|data: &[u8]| {
    check::<Reply>(data);
    check::<Command>(data);
});
