// The renderer of the exported web page: three.js, its orbit controls and Spark, in one namespace.
export * as THREE from "three";
export { OrbitControls } from "three/addons/controls/OrbitControls.js";
export { SparkRenderer, SplatMesh, SplatFileType } from "@sparkjsdev/spark";
