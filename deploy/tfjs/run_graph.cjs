// Runs a TF.js graph model with the official runtime (tfjs-core 4.22, CPU
// backend) and writes its outputs, for undream's parity test of its own
// TF.js-graph loader (undream/victims/tfjs.py). Installed by deploy/setup.sh
// (`npm ci` in this folder).
//
//   node run_graph.cjs SPEC.json
//
// SPEC.json: {"model": "path/model.json", "input": "placeholder name",
//             "shape": [1, H, W, C] (or the graph's own layout, e.g.
//             [1, C, H, W] for NanoDet), "inputs": ["a.f32", ...],
//             "outputs": ["name", ...], "out_dir": "folder"}
// Each input file is raw little-endian float32 of `shape`; for input i and
// output j the file out_dir/i_j.f32 is written (float32), and
// out_dir/outputs.json lists their names and shapes.
const fs = require('fs');
const path = require('path');
const tf = require('@tensorflow/tfjs-core');
require('@tensorflow/tfjs-backend-cpu');
const tfc = require('@tensorflow/tfjs-converter');

function readFloat32(file) {
  const raw = fs.readFileSync(file);
  return new Float32Array(raw.buffer.slice(raw.byteOffset, raw.byteOffset + raw.byteLength));
}

async function loadModel(modelJson) {
  const model = JSON.parse(fs.readFileSync(modelJson, 'utf8'));
  const specs = [];
  const buffers = [];
  for (const group of model.weightsManifest) {
    specs.push(...group.weights);
    for (const p of group.paths) buffers.push(fs.readFileSync(path.join(path.dirname(modelJson), p)));
  }
  const all = Buffer.concat(buffers);
  return tfc.loadGraphModel(tf.io.fromMemory({
    modelTopology: model.modelTopology,
    weightSpecs: specs,
    weightData: all.buffer.slice(all.byteOffset, all.byteOffset + all.byteLength),
    format: model.format,
    generatedBy: model.generatedBy,
    convertedBy: model.convertedBy,
    signature: model.signature,
    userDefinedMetadata: model.userDefinedMetadata,
  }));
}

async function main() {
  const spec = JSON.parse(fs.readFileSync(process.argv[2], 'utf8'));
  await tf.setBackend('cpu');
  const graph = await loadModel(spec.model);
  fs.mkdirSync(spec.out_dir, { recursive: true });
  const manifest = [];
  for (let i = 0; i < spec.inputs.length; i++) {
    const feeds = {};
    feeds[spec.input] = tf.tensor(readFloat32(spec.inputs[i]), spec.shape, 'float32');
    const got = graph.execute(feeds, spec.outputs);
    const list = Array.isArray(got) ? got : [got];
    const row = {};
    for (let j = 0; j < spec.outputs.length; j++) {
      const file = `${i}_${j}.f32`;
      const data = await tf.cast(list[j], 'float32').data();
      fs.writeFileSync(path.join(spec.out_dir, file), Buffer.from(data.buffer));
      row[spec.outputs[j]] = { file, shape: list[j].shape };
    }
    tf.dispose([feeds[spec.input], ...list]);
    manifest.push(row);
  }
  fs.writeFileSync(path.join(spec.out_dir, 'outputs.json'), JSON.stringify(manifest));
}

main().catch((err) => { console.error(`tfjs: ${err.message || err}`); process.exit(1); });
