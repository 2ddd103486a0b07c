//! No allocation of a model rebuild, its map and its diagnostics is larger than the model's own
//! buffers or the bounded workspace of faer's matrix product ([`PRODUCT_WORKSPACE_BYTES`]).
//!
//! faer's x86-64 product (private-gemm-x86) reserves a packing workspace once per thread that
//! runs a product, sized from the L3 cache the system reports: twice the whole machine's L3,
//! 960 MiB on a 2-vCPU VM reporting 480 MiB. A few concurrent diagnostics of older versions (a
//! rebuild each, on threads of their own) then exhausted a 10 GiB address-space limit and the
//! server aborted ("memory allocation of 1006632960 bytes failed", finding F15). The vendored,
//! patched crate (vendor/private-gemm-x86) caps that figure; this test records the largest single
//! allocation of the whole process while a model of n = 1300 points (parallel factorisation, as
//! from `PARALLEL_MIN_N`) is rebuilt from its state, predicts a 41 × 41 map and its leave-one-out
//! residuals. It runs in a binary of its own because it installs a counting global allocator.

use nalgebra::{DMatrix, DVector};
use precond_core::gp::cost::PRODUCT_WORKSPACE_BYTES;
use precond_core::gp::{GpModel, ModelState};
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

/// The system allocator, recording the largest request while [`RECORDING`] is set.
struct Largest;

static RECORDING: AtomicBool = AtomicBool::new(false);
static LARGEST: AtomicUsize = AtomicUsize::new(0);

fn record(size: usize) {
    if RECORDING.load(Ordering::Relaxed) {
        LARGEST.fetch_max(size, Ordering::Relaxed);
    }
}

// SAFETY: every call is forwarded unchanged to the system allocator; recording only reads sizes.
unsafe impl GlobalAlloc for Largest {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        record(new_size);
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOCATOR: Largest = Largest;

#[test]
fn a_rebuild_its_map_and_diagnostics_allocate_no_more_than_the_product_workspace() {
    let (n, d) = (1300, 4);
    // Inputs on a deterministic scattered lattice in the unit box; smooth labels.
    let x = DMatrix::from_fn(n, d, |i, k| ((i * (2 * k + 3) + 7 * k) % 97) as f64 / 96.0);
    let y = DVector::from_fn(n, |i, _| {
        (3.0 * x[(i, 0)]).sin() * x[(i, 1)] + 0.1 * x[(i, 2)]
    });
    let state: ModelState = serde_json::from_value(serde_json::json!({
        "format": 1,
        "noise": "homoscedastic",
        "n_train": n,
        "hyperparameters": {
            "length_scales": [0.4, 0.6, 1.5, 3.0],
            "signal_variance": 0.2,
            "noise_variance": 1e-3,
            "prior_mean": 0.0,
            "kernel": "matern32",
        },
        "jitter": 0.0,
        "log_marginal_likelihood": 0.0,
        "noise_model": null,
    }))
    .expect("a valid state");
    let side = 41;
    let grid = DMatrix::from_fn(side * side, d, |j, k| match k {
        0 => (j % side) as f64 / (side - 1) as f64,
        1 => (j / side) as f64 / (side - 1) as f64,
        _ => 0.5,
    });

    RECORDING.store(true, Ordering::Relaxed);
    let model = GpModel::from_state(&x, &y, &state).expect("the state rebuilds");
    let map = model.predict(&grid);
    let loo = model
        .leave_one_out()
        .expect("an exact GP has leave-one-out residuals");
    RECORDING.store(false, Ordering::Relaxed);

    assert!(map.mean.iter().all(|m| m.is_finite()));
    assert_eq!(loo.len(), n);
    let largest = LARGEST.load(Ordering::Relaxed);
    // The model's own buffers are n × n matrices of f64 (13.5 MB here).
    let bound = PRODUCT_WORKSPACE_BYTES.max(n * n * 8);
    assert!(
        largest <= bound,
        "an allocation of {largest} bytes ({} MiB) during a rebuild of n = {n}: more than the \
         product workspace's {PRODUCT_WORKSPACE_BYTES} bytes or the model's n² floats",
        largest >> 20
    );
}
