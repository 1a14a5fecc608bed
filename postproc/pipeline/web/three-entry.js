// The three.js classes the report's viewer uses, bundled by `npm run build` (esbuild)
// into one classic script that defines the global `THREE` (deploy/setup.sh runs it).
// A classic script can be inlined in report.html and runs from file:// (ES modules
// loaded from files are blocked there).
export * from "three";
export { OrbitControls } from "three/addons/controls/OrbitControls.js";
