// Make a .ksplat test file with @mkkellogg/gaussian-splats-3d's own converter (the test oracle).
// usage: node ksplat_convert.mjs IN.ply OUT.ksplat COMPRESSION_LEVEL SH_DEGREE
// Runs from the folder where data_tools/ksplat_oracle.py installed the pinned package and its
// `three` peer; the alpha removal threshold is 0, so every splat of the input is written.
import { readFileSync, writeFileSync } from 'node:fs';
import { pathToFileURL } from 'node:url';
import { join } from 'node:path';

const [input, output, level, degree] = process.argv.slice(2);
if (!input || !output || level === undefined || degree === undefined) {
    console.error('usage: node ksplat_convert.mjs IN.ply OUT.ksplat COMPRESSION_LEVEL SH_DEGREE');
    process.exit(2);
}
// The library schedules its parsing with window.setTimeout; node has the same timer globally.
globalThis.window ??= globalThis;
const modules = process.env.KSPLAT_ORACLE_MODULES;
const entry = join(modules, '@mkkellogg', 'gaussian-splats-3d', 'build', 'gaussian-splats-3d.module.js');
const lib = await import(pathToFileURL(entry).href);

const bytes = readFileSync(input);
const data = bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength);
const alphaThreshold = 0;
const optimize = true;   // the converter path: sections, buckets, quantisation of levels 1 and 2
const splatBuffer = await lib.PlyLoader.loadFromFileData(
    data, alphaThreshold, Number(level), optimize, Number(degree));
writeFileSync(output, new Uint8Array(splatBuffer.bufferData));
console.log(`${output}: ${splatBuffer.getSplatCount()} splats, level ${level}, SH degree ${degree}`);
