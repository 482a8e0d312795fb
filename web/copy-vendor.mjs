// Copy the few files the page (and the API's /docs) needs from node_modules into service/static/vendor,
// with each library's LICENSE, so the served page works offline and without npm.
// Run after `npm ci`:  node copy-vendor.mjs   (or `npm run vendor`)
import { cpSync, mkdirSync, rmSync, writeFileSync, readFileSync } from 'node:fs';
import { dirname, join } from 'node:path';
import { fileURLToPath } from 'node:url';

const here = dirname(fileURLToPath(import.meta.url));
const modules = join(here, 'node_modules');
const vendor = join(here, '..', 'service', 'static', 'vendor');

// [package, files relative to the package root]
const wanted = [
  ['leaflet', [
    'LICENSE',
    'dist/leaflet.js',
    'dist/leaflet.css',
    'dist/images/layers.png',
    'dist/images/layers-2x.png',
    'dist/images/marker-icon.png',
    'dist/images/marker-icon-2x.png',
    'dist/images/marker-shadow.png',
  ]],
  // /docs (Swagger UI, served by the API from here: no CDN); the bundle holds the standalone preset
  ['swagger-ui-dist', [
    'LICENSE',
    'NOTICE',
    'swagger-ui-bundle.js',
    'swagger-ui-bundle.js.LICENSE.txt',
    'swagger-ui.css',
    'favicon-32x32.png',
  ]],
  ['three', [
    'LICENSE',
    'build/three.module.js',
    'build/three.core.js',
    'examples/jsm/controls/OrbitControls.js',
    'examples/jsm/loaders/GLTFLoader.js',
    // GLTFLoader imports these two by relative path
    'examples/jsm/utils/BufferGeometryUtils.js',
    'examples/jsm/utils/SkeletonUtils.js',
  ]],
];

rmSync(vendor, { recursive: true, force: true });
const versions = {};
for (const [pkg, files] of wanted) {
  versions[pkg] = JSON.parse(readFileSync(join(modules, pkg, 'package.json'), 'utf8')).version;
  for (const file of files) {
    const target = join(vendor, pkg, file);
    mkdirSync(dirname(target), { recursive: true });
    cpSync(join(modules, pkg, file), target);
  }
}
writeFileSync(join(vendor, 'VERSIONS.json'), JSON.stringify(versions, null, 2) + '\n');
console.log(`copied into ${vendor}:`, versions);
