// The entry point of the viewer's vendored library (scripts/refresh-viewer):
// three.js, its orbit controls and Spark's splat renderer, bundled into one
// script that the generated pages inline. Nothing here runs on its own.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";

window.OmniscanViewerLib = { THREE, OrbitControls, SparkRenderer, SplatMesh };
