//! The kernel support as a compile-time constant: the inner loops are generic over it.

/// Call a function generic over the kernel support `W` (and optionally `W2 = 2 W` and
/// `L = 4 ceil(W / 2)`, the lane counts of [`SymKernel`]) with the runtime support.
macro_rules! dispatch_support {
    ($w:expr, $W:ident => $body:expr) => {
        match $w {
            2 => { const $W: usize = 2; $body }
            3 => { const $W: usize = 3; $body }
            4 => { const $W: usize = 4; $body }
            5 => { const $W: usize = 5; $body }
            6 => { const $W: usize = 6; $body }
            7 => { const $W: usize = 7; $body }
            8 => { const $W: usize = 8; $body }
            9 => { const $W: usize = 9; $body }
            10 => { const $W: usize = 10; $body }
            11 => { const $W: usize = 11; $body }
            12 => { const $W: usize = 12; $body }
            13 => { const $W: usize = 13; $body }
            14 => { const $W: usize = 14; $body }
            15 => { const $W: usize = 15; $body }
            16 => { const $W: usize = 16; $body }
            w => unreachable!("kernel support {w} is checked against MAX_SUPPORT when planning"),
        }
    };
    ($w:expr, $W:ident, $W2:ident, $L:ident => $body:expr) => {
        match $w {
            2 => { const $W: usize = 2; const $W2: usize = 4; const $L: usize = 4; $body }
            3 => { const $W: usize = 3; const $W2: usize = 6; const $L: usize = 8; $body }
            4 => { const $W: usize = 4; const $W2: usize = 8; const $L: usize = 8; $body }
            5 => { const $W: usize = 5; const $W2: usize = 10; const $L: usize = 12; $body }
            6 => { const $W: usize = 6; const $W2: usize = 12; const $L: usize = 12; $body }
            7 => { const $W: usize = 7; const $W2: usize = 14; const $L: usize = 16; $body }
            8 => { const $W: usize = 8; const $W2: usize = 16; const $L: usize = 16; $body }
            9 => { const $W: usize = 9; const $W2: usize = 18; const $L: usize = 20; $body }
            10 => { const $W: usize = 10; const $W2: usize = 20; const $L: usize = 20; $body }
            11 => { const $W: usize = 11; const $W2: usize = 22; const $L: usize = 24; $body }
            12 => { const $W: usize = 12; const $W2: usize = 24; const $L: usize = 24; $body }
            13 => { const $W: usize = 13; const $W2: usize = 26; const $L: usize = 28; $body }
            14 => { const $W: usize = 14; const $W2: usize = 28; const $L: usize = 28; $body }
            15 => { const $W: usize = 15; const $W2: usize = 30; const $L: usize = 32; $body }
            16 => { const $W: usize = 16; const $W2: usize = 32; const $L: usize = 32; $body }
            w => unreachable!("kernel support {w} is checked against MAX_SUPPORT when planning"),
        }
    };
}
