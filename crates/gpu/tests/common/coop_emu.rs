//! A plain-WGSL emulation of wgpu's cooperative-matrix operations, so kernels written for tensor
//! cores run (slowly) on any adapter with f16, e.g. lavapipe. Semantics (those under which
//! `linear_coop.wgsl` was checked on an H100, and which `tests/linear.rs` re-checks through this
//! emulation): a 16×16 matrix is `m[r·16 + c]`; `coopLoadT(&a[i], st)` reads row-major
//! (`a[i + r·st + c]`), `coopLoad(&a[i], st)` column-major (`a[i + c·st + r]`), `coopStoreT` writes
//! row-major, `coopMultiplyAdd(a, b, c) = a·b + c`. Every entry point with cooperative-matrix
//! operations must start with `let n = load_n(lid);` and take its subgroups as consecutive runs
//! of 32 invocations (`lid / 32`, as on the H100): lane `lid % 32 == 0` of each subgroup does each
//! whole operation of its subgroup (the other lanes hold zero matrices), so workgroups of one or
//! several subgroups of 32 are emulated alike whatever the adapter's real subgroup size.

pub fn emulate(source: &str) -> String {
    // Without comments (they name the coop ops too).
    let src: String = source
        .lines()
        .map(|l| format!("{}\n", l.split("//").next().unwrap_or("")))
        .collect();
    let src = src.replace("enable wgpu_cooperative_matrix;\n", "");
    assert!(!src.contains("wgpu_cooperative_matrix"));
    let src = src
        .replace("coop_mat16x16<f32, C>()", "array<f32, 256>()")
        .replace("coop_mat16x16<f16, A>()", "array<f32, 256>()")
        .replace("coop_mat16x16<f16, B>()", "array<f32, 256>()").replace("coopMultiplyAdd(", "emu_mma(");
    // Each entry point with coop ops starts with `let n = load_n(lid);`: record the lane within
    // its subgroup of 32 (`lid` itself in workgroups of one subgroup: lavapipe takes minutes to
    // compile the backward kernels of linear_coop.wgsl when the lane is written `lid % 32u`).
    let src = {
        let marker = "let n = load_n(lid);";
        let (mut out, mut last) = (String::new(), 0);
        for (at, _) in src.match_indices(marker) {
            let size_at = src[..at].rfind("@workgroup_size(").expect("an entry point with coop ops has a @workgroup_size") + 16;
            let size = src[size_at..].split(')').next().unwrap_or("").trim();
            let lane = if size == "32" || size == "32u" { "lid" } else { "lid % 32u" };
            out.push_str(&src[last..at]);
            out.push_str(&format!("emu_lane = {lane};\n    {marker}"));
            last = at + marker.len();
        }
        out.push_str(&src[last..]);
        out
    };
    let mut out = String::new();
    let mut funcs = std::collections::BTreeMap::new();
    let mut rest = src.as_str();
    // Loads: coopLoad[T]<coop_mat16x16<f16, R>>(&ARRAY[INDEX], STRIDE)
    while let Some(at) = rest.find("coopLoad") {
        out.push_str(&rest[..at]);
        let tail = &rest[at..];
        let row_major = tail.starts_with("coopLoadT<");
        let args_at = tail.find(">>(").expect("coop load type arguments") + 3;
        let (close, args) = call_args(tail, args_at);
        assert_eq!(args.len(), 2, "coop load: two arguments");
        let (ptr, stride) = (args[0], args[1]);
        let ptr = ptr.strip_prefix('&').expect("coop load: a pointer");
        let (array, index) = ptr.strip_suffix(']').and_then(|p| p.split_once('[')).expect("coop load: &array[index]");
        let name = format!("emu_load_{}_{array}", if row_major { "rm" } else { "cm" });
        let elem = if row_major { "i + r * st + c" } else { "i + c * st + r" };
        funcs.entry(name.clone()).or_insert(format!(
            "fn {name}(i: u32, st: u32) -> array<f32, 256> {{\n    var m = array<f32, 256>();\n    if emu_lane != 0u {{ return m; }}\n    \
             for (var r = 0u; r < 16u; r++) {{\n        for (var c = 0u; c < 16u; c++) {{\n            \
             m[r * 16u + c] = f32({array}[{elem}]);\n        }}\n    }}\n    return m;\n}}\n"
        ));
        out.push_str(&format!("{name}({index}, {stride})"));
        rest = &tail[close + 1..];
    }
    out.push_str(rest);
    // Stores: coopStoreT(MATRIX, &ARRAY[INDEX], STRIDE);
    let src = out;
    let mut out = String::new();
    let mut rest = src.as_str();
    while let Some(at) = rest.find("coopStoreT(") {
        out.push_str(&rest[..at]);
        let tail = &rest[at + "coopStoreT(".len()..];
        let (close, parts) = call_args(tail, 0);
        assert_eq!(parts.len(), 3, "coop store: {}", &tail[..close]);
        let ptr = parts[1].strip_prefix('&').expect("coop store: a pointer");
        let (array, index) = ptr.strip_suffix(']').and_then(|p| p.split_once('[')).expect("coop store: &array[index]");
        let name = format!("emu_store_{array}");
        funcs.entry(name.clone()).or_insert(format!(
            "fn {name}(m_in: array<f32, 256>, i: u32, st: u32) {{\n    if emu_lane != 0u {{ return; }}\n    var m = m_in;\n    \
             for (var r = 0u; r < 16u; r++) {{\n        for (var c = 0u; c < 16u; c++) {{\n            \
             {array}[i + r * st + c] = m[r * 16u + c];\n        }}\n    }}\n}}\n"
        ));
        out.push_str(&format!("{name}({}, {index}, {})", parts[0], parts[2]));
        rest = &tail[close + 1..];
    }
    out.push_str(rest);
    for op in ["coopLoad", "coopStore", "coopMultiplyAdd", "coop_mat"] {
        assert!(!out.contains(op), "an unemulated {op} is left");
    }
    out.push_str(
        "\nvar<private> emu_lane: u32;\n\
         fn emu_mma(a_in: array<f32, 256>, b_in: array<f32, 256>, c_in: array<f32, 256>) -> array<f32, 256> {\n\
         \x20   var d = c_in;\n    if emu_lane != 0u { return d; }\n    var a = a_in;\n    var b = b_in;\n\
         \x20   for (var r = 0u; r < 16u; r++) {\n        for (var c = 0u; c < 16u; c++) {\n\
         \x20           var s = d[r * 16u + c];\n            for (var k = 0u; k < 16u; k++) { s += a[r * 16u + k] * b[k * 16u + c]; }\n\
         \x20           d[r * 16u + c] = s;\n        }\n    }\n    return d;\n}\n",
    );
    for f in funcs.values() {
        out.push_str(f);
    }
    out
}


/// The arguments of a call whose argument list starts at `tail[start..]` (just after its `(`):
/// (index of the closing `)`, the top-level comma-separated arguments, trimmed).
fn call_args(tail: &str, start: usize) -> (usize, Vec<&str>) {
    let (mut depth, mut args, mut from) = (0i32, Vec::new(), start);
    for (i, ch) in tail[start..].char_indices() {
        let i = start + i;
        match ch {
            '(' | '[' => depth += 1,
            ')' | ']' if depth > 0 => depth -= 1,
            ')' => {
                args.push(tail[from..i].trim());
                return (i, args);
            }
            ',' if depth == 0 => {
                args.push(tail[from..i].trim());
                from = i + 1;
            }
            _ => {}
        }
    }
    panic!("unbalanced call: {}", &tail[start..tail.len().min(start + 80)]);
}
