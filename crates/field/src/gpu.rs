//! The GPU side of the field seam: a field that can run on a wgpu device offers a
//! [`GpuRadianceField`] twin of itself through [`RadianceField::to_gpu`](crate::RadianceField::to_gpu).
//!
//! The twin starts from the CPU field's parameters (same initialisation, same seed) and keeps them
//! on the device as one buffer per parameter group, in exactly the layout of
//! [`RadianceField::export_params`](crate::RadianceField::export_params): checkpoints move between
//! devices unchanged. Its methods only *record* kernels into the caller's command encoder, so the
//! trainer can put a whole step (sampling, field, compositing, loss, backward, Adam) into one
//! submission with no host round trip. Batch sizes are only known on the device: the number of
//! samples is `counters[COUNTER_N_SAMPLES]`, and every kernel is launched for `capacity` samples.

pub use nerf_gpu::wgpu;
use nerf_gpu::compact::{GpuRowCopy, RowOffsets};
use nerf_gpu::GpuContext;

/// One parameter group on the device.
pub struct GpuParamGroup {
    /// Group name (as [`ParamGroupMut::name`](crate::ParamGroupMut)), keys optimiser state and checkpoints.
    pub name: String,
    /// Number of parameters.
    pub len: usize,
    /// L2 weight decay of the group.
    pub weight_decay: f32,
    /// The parameters (`len` f32).
    pub params: wgpu::Buffer,
    /// Their gradients (`len` f32), accumulated by `record_backward`, zeroed by the optimiser.
    pub grads: wgpu::Buffer,
}

/// Device buffers of a packed batch of samples as a field reads them.
#[derive(Clone, Copy)]
pub struct GpuSamples<'a> {
    /// `counters` (`[1]` = number of samples).
    pub counters: &'a wgpu::Buffer,
    /// Positions, `3·n` f32.
    pub positions: &'a wgpu::Buffer,
    /// Unit directions, `3·n` f32.
    pub dirs: &'a wgpu::Buffer,
    /// The most samples the buffers hold (the launch size).
    pub capacity: usize,
}

impl GpuSamples<'_> {
    /// The launch size of a field built for `field_capacity` samples on this batch: the batch's
    /// capacity, which may be smaller than the field's (e.g. the last chunk of a
    /// [`ChunkedDensity`]). Panics when the batch claims more samples than the field's buffers
    /// hold.
    pub fn launch(&self, field_capacity: usize) -> usize {
        assert!(
            self.capacity <= field_capacity,
            "a batch of {} samples for a field built for {field_capacity}",
            self.capacity
        );
        self.capacity
    }
}

/// A radiance field on a wgpu device (the twin of a CPU [`RadianceField`](crate::RadianceField)).
/// Buffers are sized once, for the `capacity` given at creation.
pub trait GpuRadianceField: Send {
    /// The registry name of the field kind.
    fn kind(&self) -> &'static str;

    /// Most samples per launch.
    fn capacity(&self) -> usize;

    /// The parameter groups on the device, in `export_params` order.
    fn groups(&self) -> &[GpuParamGroup];

    /// Records the density query (σ ≥ 0 per sample) — occupancy-grid updates.
    fn record_density(&self, ctx: &GpuContext, enc: &mut wgpu::CommandEncoder, s: GpuSamples<'_>, sigma: &wgpu::Buffer);

    /// Records inference: σ and rgb per sample (rendering).
    fn record_query(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        sigma: &wgpu::Buffer,
        rgb: &wgpu::Buffer,
    );

    /// Records the training forward (keeps what the backward needs in the field's own buffers).
    fn record_forward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        sigma: &wgpu::Buffer,
        rgb: &wgpu::Buffer,
    );

    /// Prepares the field to keep what its density pass over up to `marched` samples computes
    /// ([`record_density_for_training`](Self::record_density_for_training)) for
    /// [`record_forward_rows`](Self::record_forward_rows) (training on compacted samples). The
    /// default keeps nothing; the hash field keeps its position encodings (`marched` rows of
    /// them: buffers are sized here, once).
    fn keep_density_pass(&mut self, ctx: &GpuContext, marched: usize) -> Result<(), crate::FieldError> {
        let _ = (ctx, marched);
        Ok(())
    }

    /// Whether [`record_density_for_training`](Self::record_density_for_training) reads and
    /// writes its chunk in place: given the marched batch's own buffers (`s.positions` and
    /// `sigma` hold every row, `s.capacity` is the chunk's size), it reads the positions of rows
    /// `first_row..` and writes their σ there itself (binding the buffers at the chunk's offset,
    /// [`nerf_gpu::Bound`]), so [`ChunkedDensity`] copies nothing in or out. Default `false`:
    /// every chunk after the first comes in chunk buffers of its own.
    fn density_pass_in_place(&self) -> bool {
        false
    }

    /// Records the density pass of a step on compacted samples over rows `first_row..` of the
    /// marched batch (one chunk of a [`ChunkedDensity`]): σ as
    /// [`record_density`](Self::record_density), and whatever the field keeps for
    /// [`record_forward_rows`](Self::record_forward_rows). The buffers are the chunk's own, or
    /// the whole batch's where the field reads in place
    /// ([`density_pass_in_place`](Self::density_pass_in_place)). Default: `record_density`.
    fn record_density_for_training(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        sigma: &wgpu::Buffer,
        first_row: usize,
    ) {
        let _ = first_row;
        self.record_density(ctx, enc, s, sigma);
    }

    /// Records the training forward of `s`, the compaction of the samples of the density pass
    /// recorded last (by `record_density_for_training`, with the same parameters): sample `b` of
    /// `s` is row `rows[b]` of that pass (u32, as `GpuCompactor`'s `out_rows`). Same results as
    /// [`record_forward`](Self::record_forward) (the default), which a field may beat by
    /// reusing what the pass computed.
    fn record_forward_rows(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        rows: &wgpu::Buffer,
        sigma: &wgpu::Buffer,
        rgb: &wgpu::Buffer,
    ) {
        let _ = rows;
        self.record_forward(ctx, enc, s, sigma, rgb);
    }

    /// Records the backward of the last recorded forward: dL/dσ (`n`) and dL/drgb (`3·n`) in,
    /// parameter gradients *accumulated* into the groups' `grads`.
    fn record_backward(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        d_sigma: &wgpu::Buffer,
        d_rgb: &wgpu::Buffer,
    );

    /// Prepares the twin to give its gradients in its inputs
    /// ([`record_input_gradients`](Self::record_input_gradients)): camera pose refinement
    /// (`nerf_rays::pose`), the GPU side of
    /// [`RadianceField::backward_with_inputs`](crate::RadianceField::backward_with_inputs). Called
    /// once, before any step is recorded; the default returns [`FieldError::Unsupported`](crate::FieldError::Unsupported).
    fn enable_input_gradients(&mut self, ctx: &GpuContext) -> Result<(), crate::FieldError> {
        let _ = ctx;
        Err(crate::FieldError::Unsupported { field: self.kind().into(), what: "input gradients on the GPU (camera pose refinement)".into() })
    }

    /// Records, after [`record_backward`](Self::record_backward) of the same samples, dL/d(position)
    /// into `d_positions` and dL/d(direction) into `d_dirs` (`3·n` each, *written*) for every
    /// sample, as [`RadianceField::backward_with_inputs`](crate::RadianceField::backward_with_inputs)
    /// does on the CPU. Only valid once [`enable_input_gradients`](Self::enable_input_gradients)
    /// succeeded; the default panics (no field offers it without that).
    fn record_input_gradients(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        s: GpuSamples<'_>,
        d_positions: &wgpu::Buffer,
        d_dirs: &wgpu::Buffer,
    ) {
        let _ = (ctx, enc, s, d_positions, d_dirs);
        panic!("field `{}` has no input gradients on the GPU (enable_input_gradients refuses)", self.kind())
    }

    /// Reads the parameters back, as [`RadianceField::export_params`](crate::RadianceField::export_params).
    fn export_params(&self, ctx: &GpuContext) -> Result<Vec<(String, Vec<f32>)>, nerf_gpu::GpuError> {
        self.groups().iter().map(|g| Ok((g.name.clone(), ctx.read_f32(&g.params, g.len)?))).collect()
    }

    /// Uploads parameters written by `export_params` (either device's).
    fn import_params(&self, ctx: &GpuContext, groups: &[(String, Vec<f32>)]) -> Result<(), crate::FieldError> {
        let mine = self.groups();
        if mine.len() != groups.len() {
            return Err(crate::FieldError::ParamMismatch {
                group: "*".into(),
                message: format!("expected {} groups, got {}", mine.len(), groups.len()),
            });
        }
        for (g, (name, values)) in mine.iter().zip(groups) {
            if &g.name != name || g.len != values.len() {
                return Err(crate::FieldError::ParamMismatch {
                    group: name.clone(),
                    message: format!("expected `{}` with {} values, got `{}` with {}", g.name, g.len, name, values.len()),
                });
            }
            ctx.write(&g.params, 0, values);
        }
        Ok(())
    }
}

/// A field's density query over a batch larger than the field's capacity (the marched samples of
/// training on compacted samples): the batch is cut into chunks of the field's capacity; the
/// first chunk is read and written in place, every later one goes through chunk buffers
/// (positions copied in, σ copied out, [`GpuRowCopy`]: only the
/// chunk's samples, not its capacity), each with its sample count computed on the device from
/// the batch's `counters[1]` — except in the density pass of a field that reads its chunks in
/// place ([`GpuRadianceField::density_pass_in_place`]), which copies nothing. Buffers and
/// uniforms are made once.
pub struct ChunkedDensity {
    total: usize,
    glue: nerf_gpu::TrainGlue,
    /// (offset, size, chunk uniform, copy offsets in and out) per chunk.
    chunks: Vec<(usize, usize, wgpu::Buffer, RowOffsets, RowOffsets)>,
    counters: wgpu::Buffer,
    points: wgpu::Buffer,
    dirs: wgpu::Buffer,
    sigma: wgpu::Buffer,
    /// Copies of rows of 3 (positions) and 1 (σ) floats, launched from the chunk's count.
    copy_points: GpuRowCopy,
    copy_sigma: GpuRowCopy,
    args: nerf_gpu::DispatchArgs,
}

impl ChunkedDensity {
    /// For batches of up to `total` samples and a field of capacity `chunk`.
    pub fn new(ctx: &GpuContext, chunk: usize, total: usize) -> Self {
        let chunk = chunk.max(1);
        let glue = nerf_gpu::TrainGlue::new(ctx, 1, nerf_gpu::composite::BatchParams::default());
        let chunks = (0..total.max(1))
            .step_by(chunk)
            .map(|o| {
                let size = chunk.min(total.max(1) - o);
                (o, size, nerf_gpu::TrainGlue::chunk_uniform(ctx, o, chunk), GpuRowCopy::offsets(ctx, o, 0), GpuRowCopy::offsets(ctx, 0, o))
            })
            .collect();
        let spill = if total > chunk { chunk } else { 1 };
        Self {
            total,
            glue,
            chunks,
            counters: ctx.zeros("density chunk counters", 16),
            points: ctx.zeros("density chunk points", 12 * spill),
            dirs: ctx.zeros("density chunk dirs", 12 * spill),
            sigma: ctx.zeros("density chunk sigma", 4 * spill),
            copy_points: GpuRowCopy::new(ctx, 3).expect("rows of 3 floats"),
            copy_sigma: GpuRowCopy::new(ctx, 1).expect("rows of 1 float"),
            args: nerf_gpu::DispatchArgs::new(ctx, chunk),
        }
    }

    /// Records σ of the first `counters[1]` (≤ `total`) samples of `positions` (`[total][3]`)
    /// into `sigma` (`[total]`) with `field` (whose capacity is at least the chunk size).
    pub fn record(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        field: &dyn GpuRadianceField,
        counters: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        sigma: &wgpu::Buffer,
    ) {
        self.record_chunks(ctx, enc, counters, positions, sigma, false, &mut |enc, s, sigma, _| field.record_density(ctx, enc, s, sigma));
    }

    /// As [`record`](Self::record), the density pass of a step on compacted samples: each chunk
    /// through [`GpuRadianceField::record_density_for_training`] with its first row, so the
    /// field can keep what it computes for [`GpuRadianceField::record_forward_rows`].
    pub fn record_for_training(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        field: &dyn GpuRadianceField,
        counters: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        sigma: &wgpu::Buffer,
    ) {
        self.record_chunks(ctx, enc, counters, positions, sigma, field.density_pass_in_place(), &mut |enc, s, sigma, first_row| {
            field.record_density_for_training(ctx, enc, s, sigma, first_row)
        });
    }

    /// The chunks: `query(enc, samples, σ out, first row)` per chunk; in the batch's own buffers
    /// for the first chunk, and for every chunk where the query reads `in_place`.
    #[allow(clippy::too_many_arguments)]
    fn record_chunks(
        &self,
        ctx: &GpuContext,
        enc: &mut wgpu::CommandEncoder,
        counters: &wgpu::Buffer,
        positions: &wgpu::Buffer,
        sigma: &wgpu::Buffer,
        in_place: bool,
        query: &mut dyn FnMut(&mut wgpu::CommandEncoder, GpuSamples<'_>, &wgpu::Buffer, usize),
    ) {
        assert!(
            positions.size() >= 12 * self.total as u64 && sigma.size() >= 4 * self.total as u64,
            "ChunkedDensity: buffers hold fewer than {} samples",
            self.total
        );
        for (offset, size, uniform, copy_in, copy_out) in &self.chunks {
            self.glue.record_chunk_count(ctx, enc, uniform, counters, &self.counters);
            if *offset == 0 || in_place {
                // (A density query reads no directions.)
                let s = GpuSamples { counters: &self.counters, positions, dirs: positions, capacity: *size };
                query(enc, s, sigma, *offset);
            } else {
                let launch = self.args.record(ctx, enc, &self.counters, *size);
                self.copy_points.record(ctx, enc, &self.counters, copy_in, positions, &self.points, launch);
                let s = GpuSamples { counters: &self.counters, positions: &self.points, dirs: &self.dirs, capacity: *size };
                query(enc, s, &self.sigma, *offset);
                self.copy_sigma.record(ctx, enc, &self.counters, copy_out, &self.sigma, sigma, launch);
            }
        }
    }
}

/// Conformance check of a GPU twin against its CPU field (used by each field's tests): on `n`
/// random samples in the box (random unit directions), density, query and training forward must
/// match within `tol` (relative to the largest value) and the parameter gradients of a backward
/// pass with random upstream gradients within `grad_tol`; export/import must round-trip.
/// Panics with the first mismatch.
pub fn check_gpu_twin(
    cpu: &mut dyn crate::RadianceField,
    ctx: &GpuContext,
    aabb: ([f32; 3], [f32; 3]),
    n: usize,
    seed: u64,
    tol: f32,
    grad_tol: f32,
) {
    use rand::Rng as _;
    let capacity = n + 37;
    let gpu = cpu.to_gpu(ctx, capacity).expect("the field has a GPU twin").expect("the twin builds");
    let mut rng = nerf_core::rng(seed, 0);
    let (lo, hi) = aabb;
    let pos: Vec<f32> = (0..3 * n).map(|i| rng.gen_range(lo[i % 3]..hi[i % 3])).collect();
    let dirs: Vec<f32> = (0..n)
        .flat_map(|_| {
            let d = [rng.gen_range(-1.0f32..1.0), rng.gen_range(-1.0f32..1.0), rng.gen_range(0.1f32..1.0)];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            d.map(|x| x / l)
        })
        .collect();
    let close = |what: &str, gpu: &[f32], cpu: &[f32], tol: f32| {
        assert_eq!(gpu.len(), cpu.len(), "{what}");
        let scale = cpu.iter().fold(0.0f32, |m, x| m.max(x.abs())).max(1e-6);
        for (i, (a, b)) in gpu.iter().zip(cpu).enumerate() {
            assert!(a.is_finite(), "{what}[{i}] not written: {a}");
            assert!((a - b).abs() <= tol * scale, "{what}[{i}]: gpu {a} vs cpu {b} (scale {scale})");
        }
    };
    let pad = |v: &[f32], len: usize| {
        let mut p = v.to_vec();
        p.resize(len, 0.0);
        p
    };
    let counters = ctx.upload("counters", &[0u32, n as u32]);
    let positions = ctx.upload("positions", &pad(&pos, 3 * capacity));
    let d = ctx.upload("dirs", &pad(&dirs, 3 * capacity));
    let s = GpuSamples { counters: &counters, positions: &positions, dirs: &d, capacity };
    let sigma = ctx.upload("sigma", &vec![f32::NAN; capacity]);
    let rgb = ctx.upload("rgb", &vec![f32::NAN; 3 * capacity]);
    let run = |f: &dyn Fn(&mut wgpu::CommandEncoder)| {
        let mut enc = ctx.encoder("twin");
        f(&mut enc);
        ctx.queue.submit([enc.finish()]);
    };

    run(&|enc| gpu.record_query(ctx, enc, s, &sigma, &rgb));
    let (mut cs, mut cc) = (vec![0.0; n], vec![0.0; 3 * n]);
    cpu.query(&pos, &dirs, &mut cs, &mut cc);
    close("query sigma", &ctx.read_f32(&sigma, n).unwrap(), &cs, tol);
    close("query rgb", &ctx.read_f32(&rgb, 3 * n).unwrap(), &cc, tol);

    ctx.write(&sigma, 0, &vec![f32::NAN; capacity]);
    run(&|enc| gpu.record_density(ctx, enc, s, &sigma));
    let mut ds = vec![0.0; n];
    cpu.density(&pos, &mut ds);
    close("density", &ctx.read_f32(&sigma, n).unwrap(), &ds, tol);

    let d_sigma: Vec<f32> = (0..n).map(|_| rng.gen_range(-0.1f32..0.1)).collect();
    let d_rgb: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let dsb = ctx.upload("d_sigma", &pad(&d_sigma, capacity));
    let drb = ctx.upload("d_rgb", &pad(&d_rgb, 3 * capacity));
    run(&|enc| {
        gpu.record_forward(ctx, enc, s, &sigma, &rgb);
        gpu.record_backward(ctx, enc, s, &dsb, &drb);
    });
    cpu.zero_grad();
    cpu.forward(&pos, &dirs, &mut cs, &mut cc);
    cpu.backward(&d_sigma, &d_rgb);
    close("forward sigma", &ctx.read_f32(&sigma, n).unwrap(), &cs, tol);
    close("forward rgb", &ctx.read_f32(&rgb, 3 * n).unwrap(), &cc, tol);
    let groups = cpu.param_groups();
    assert_eq!(groups.len(), gpu.groups().len());
    for (g, cg) in gpu.groups().iter().zip(groups) {
        assert_eq!(g.name, cg.name);
        assert_eq!(g.weight_decay, cg.weight_decay, "weight decay of {}", g.name);
        close(&format!("grad {}", g.name), &ctx.read_f32(&g.grads, g.len).unwrap(), cg.grads, grad_tol);
    }
    let exported = gpu.export_params(ctx).unwrap();
    assert_eq!(exported, cpu.export_params());
    gpu.import_params(ctx, &exported).unwrap();
    let mut bad = exported.clone();
    bad[0].1.pop();
    assert!(gpu.import_params(ctx, &bad).is_err());
}

/// Conformance check of a GPU twin's input gradients (camera pose refinement) against its CPU
/// field's [`backward_with_inputs`](crate::RadianceField::backward_with_inputs), used by the
/// fields' tests: on `n` random samples in the box, after the twin's
/// [`enable_input_gradients`](GpuRadianceField::enable_input_gradients), a training forward and
/// backward with random upstream gradients and
/// [`record_input_gradients`](GpuRadianceField::record_input_gradients), ∂L/∂x and ∂L/∂dir must
/// match within `tol` (relative to the largest value), the parameter gradients within
/// `grad_tol`, and the rows past the batch's count stay as they were. Panics with the first
/// mismatch.
#[allow(clippy::too_many_arguments)]
pub fn check_gpu_input_gradients(
    cpu: &mut dyn crate::RadianceField,
    ctx: &GpuContext,
    aabb: ([f32; 3], [f32; 3]),
    n: usize,
    seed: u64,
    tol: f32,
    grad_tol: f32,
) {
    use rand::Rng as _;
    let capacity = n + 37;
    let mut gpu = cpu.to_gpu(ctx, capacity).expect("the field has a GPU twin").expect("the twin builds");
    gpu.enable_input_gradients(ctx).expect("the twin gives input gradients");
    let mut rng = nerf_core::rng(seed, 1);
    let (lo, hi) = aabb;
    let pos: Vec<f32> = (0..3 * n).map(|i| rng.gen_range(lo[i % 3]..hi[i % 3])).collect();
    let dirs: Vec<f32> = (0..n)
        .flat_map(|_| {
            let d = [rng.gen_range(-1.0f32..1.0), rng.gen_range(-1.0f32..1.0), rng.gen_range(-1.0f32..1.0)];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
            d.map(|x| x / l)
        })
        .collect();
    let pad = |v: &[f32], len: usize| {
        let mut p = v.to_vec();
        p.resize(len, f32::NAN);
        p
    };
    let counters = ctx.upload("counters", &[0u32, n as u32]);
    let positions = ctx.upload("positions", &pad(&pos, 3 * capacity));
    let d = ctx.upload("dirs", &pad(&dirs, 3 * capacity));
    let s = GpuSamples { counters: &counters, positions: &positions, dirs: &d, capacity };
    let sigma = ctx.upload("sigma", &vec![f32::NAN; capacity]);
    let rgb = ctx.upload("rgb", &vec![f32::NAN; 3 * capacity]);
    let d_sigma: Vec<f32> = (0..n).map(|_| rng.gen_range(-0.1f32..0.1)).collect();
    let d_rgb: Vec<f32> = (0..3 * n).map(|_| rng.gen_range(-1.0f32..1.0)).collect();
    let dsb = ctx.upload("d_sigma", &pad(&d_sigma, capacity));
    let drb = ctx.upload("d_rgb", &pad(&d_rgb, 3 * capacity));
    let poison = 1.0e30f32;
    let d_pos = ctx.upload("d_positions", &vec![poison; 3 * capacity]);
    let d_dir = ctx.upload("d_dirs", &vec![poison; 3 * capacity]);
    let mut enc = ctx.encoder("twin input gradients");
    gpu.record_forward(ctx, &mut enc, s, &sigma, &rgb);
    gpu.record_backward(ctx, &mut enc, s, &dsb, &drb);
    gpu.record_input_gradients(ctx, &mut enc, s, &d_pos, &d_dir);
    ctx.queue.submit([enc.finish()]);

    cpu.zero_grad();
    let (mut cs, mut cc) = (vec![0.0; n], vec![0.0; 3 * n]);
    cpu.forward(&pos, &dirs, &mut cs, &mut cc);
    let (mut want_pos, mut want_dir) = (vec![f32::NAN; 3 * n], vec![f32::NAN; 3 * n]);
    cpu.backward_with_inputs(&d_sigma, &d_rgb, &mut want_pos, &mut want_dir).expect("the CPU field gives input gradients");
    let close = |what: &str, gpu: &[f32], cpu: &[f32], tol: f32| {
        let scale = cpu.iter().fold(0.0f32, |m, x| m.max(x.abs())).max(1e-6);
        assert!(cpu.iter().any(|x| *x != 0.0), "{what}: the CPU gradient is all zero, the check would prove nothing");
        for (i, (a, b)) in gpu.iter().zip(cpu).enumerate() {
            assert!((a - b).abs() <= tol * scale, "{what}[{i}]: gpu {a} vs cpu {b} (scale {scale})");
        }
    };
    let got_pos = ctx.read_f32(&d_pos, 3 * capacity).unwrap();
    let got_dir = ctx.read_f32(&d_dir, 3 * capacity).unwrap();
    close("d_positions", &got_pos[..3 * n], &want_pos, tol);
    close("d_dirs", &got_dir[..3 * n], &want_dir, tol);
    assert!(got_pos[3 * n..].iter().chain(&got_dir[3 * n..]).all(|&x| x == poison), "rows past the count were written");
    let groups = cpu.param_groups();
    for (g, cg) in gpu.groups().iter().zip(groups) {
        close(&format!("grad {} (with input gradients)", g.name), &ctx.read_f32(&g.grads, g.len).unwrap(), cg.grads, grad_tol);
    }
}
