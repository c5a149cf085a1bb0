#!/usr/bin/env bash
# openfoam_sphere_duct.sh -- body-fitted reference for the settling sphere: the steady drag on a sphere
# held on the axis of a square duct whose walls and inflow move past it at U (the frame of a sphere
# settling at U through still liquid in an infinite duct), with Debian's OpenFOAM (simpleFoam,
# snappyHexMesh). ten Cate et al.'s (2002) cross-section: 100 × 100 mm, sphere d = 15 mm, 150 mm
# behind the inlet, 250 mm before the outlet.
#
# Usage:  bench/openfoam_sphere_duct.sh RHO MU U [LEVEL]
#   RHO (kg/m³), MU (Pa s), U (m/s); LEVEL: snappyHexMesh refinement of the sphere's surface over a
#   5 mm background (3: 0.625 mm, 24 cells per diameter, ≈ 57k cells, ≈ 20 s on 2 ranks; 4: 48).
# Prints one line:  openfoam_duct rho=… mu=… U=… level=… cells=… iterations=… drag=… (N, along the flow)
set -euo pipefail
export WM_PROJECT_DIR=${WM_PROJECT_DIR:-/usr/share/openfoam}   # Debian: enough to find etc/
rho=$1 mu=$2 U=$3 level=${4:-3}
command -v simpleFoam >/dev/null || { echo "openfoam_sphere_duct.sh: simpleFoam not found (Debian package openfoam)" >&2; exit 2; }
work=$(mktemp -d /tmp/pmpm_of_duct.XXXXXX)
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/system" "$work/constant" "$work/0"
cd "$work"
nu=$(awk -v m="$mu" -v r="$rho" 'BEGIN{printf "%.12g", m/r}')
hdr() { printf 'FoamFile\n{\n    version 2.0;\n    format ascii;\n    class %s;\n    object %s;\n}\n' "$1" "$2"; }
{ hdr dictionary blockMeshDict; cat <<END
scale 1;
vertices ( (0 0 0) (0.4 0 0) (0.4 0.1 0) (0 0.1 0) (0 0 0.1) (0.4 0 0.1) (0.4 0.1 0.1) (0 0.1 0.1) );
blocks ( hex (0 1 2 3 4 5 6 7) (80 20 20) simpleGrading (1 1 1) );
edges ();
boundary
(
    inlet  { type patch; faces ((0 4 7 3)); }
    outlet { type patch; faces ((1 2 6 5)); }
    walls  { type wall; faces ((3 7 6 2) (1 5 4 0) (0 3 2 1) (4 5 6 7)); }
);
mergePatchPairs ();
END
} >system/blockMeshDict
{ hdr dictionary snappyHexMeshDict; cat <<END
castellatedMesh true;
snap            true;
addLayers       false;
geometry
{
    ball { type searchableSphere; centre (0.15 0.05 0.05); radius 0.0075; }
    near { type searchableSphere; centre (0.15 0.05 0.05); radius 0.02; }
    wake { type searchableBox; min (0.13 0.035 0.035); max (0.22 0.065 0.065); }
}
castellatedMeshControls
{
    maxLocalCells 4000000; maxGlobalCells 8000000; minRefinementCells 0; nCellsBetweenLevels 2;
    maxLoadUnbalance 0.1; features (); resolveFeatureAngle 30; allowFreeStandingZoneFaces true;
    refinementSurfaces { ball { level ($level $level); patchInfo { type wall; } } }
    refinementRegions { near { mode inside; levels ((1e15 $((level - 1)))); } wake { mode inside; levels ((1e15 $((level - 2)))); } }
    locationInMesh (0.02 0.021 0.023);
}
snapControls { nSmoothPatch 3; tolerance 2.0; nSolveIter 50; nRelaxIter 5; nFeatureSnapIter 10; }
addLayersControls { relativeSizes true; layers {} expansionRatio 1.0; finalLayerThickness 0.3; minThickness 0.1;
    nGrow 0; featureAngle 60; nRelaxIter 3; nSmoothSurfaceNormals 1; nSmoothNormals 3; nSmoothThickness 10;
    maxFaceThicknessRatio 0.5; maxThicknessToMedialRatio 0.3; minMedialAxisAngle 90; nBufferCellsNoExtrude 0; nLayerIter 50; }
meshQualityControls { maxNonOrtho 65; maxBoundarySkewness 20; maxInternalSkewness 4; maxConcave 80; minVol 1e-30;
    minTetQuality 1e-30; minArea -1; minTwist 0.02; minDeterminant 0.001; minFaceWeight 0.05; minVolRatio 0.01;
    minTriangleTwist -1; nSmoothScale 4; errorReduction 0.75; }
mergeTolerance 1e-6;
END
} >system/snappyHexMeshDict
{ hdr dictionary controlDict; cat <<END
application simpleFoam; startFrom latestTime; startTime 0; stopAt endTime; endTime 5000; deltaT 1;
writeControl timeStep; writeInterval 5000; purgeWrite 1; writeFormat ascii; writePrecision 10;
writeCompression off; timeFormat general; timePrecision 6; runTimeModifiable false;
functions
{
    forces { type forces; libs ("libforces.so"); writeControl timeStep; writeInterval 10;
             patches (ball); rho rhoInf; rhoInf $rho; CofR (0.15 0.05 0.05); }
}
END
} >system/controlDict
{ hdr dictionary fvSchemes; cat <<'END'
ddtSchemes { default steadyState; }
gradSchemes { default Gauss linear; }
divSchemes { default none; div(phi,U) bounded Gauss linear; div((nuEff*dev2(T(grad(U))))) Gauss linear; }
laplacianSchemes { default Gauss linear corrected; }
interpolationSchemes { default linear; }
snGradSchemes { default corrected; }
END
} >system/fvSchemes
{ hdr dictionary fvSolution; cat <<'END'
solvers
{
    p { solver GAMG; smoother GaussSeidel; tolerance 1e-10; relTol 0.01; }
    U { solver smoothSolver; smoother symGaussSeidel; tolerance 1e-12; relTol 0.05; }
}
SIMPLE { nNonOrthogonalCorrectors 1; consistent yes; residualControl { p 1e-8; U 1e-9; } }
relaxationFactors { equations { U 0.9; ".*" 0.9; } fields { p 1.0; } }
END
} >system/fvSolution
{ hdr dictionary decomposeParDict; echo "numberOfSubdomains 2; method simple; simpleCoeffs { n (2 1 1); delta 0.001; }"; } >system/decomposeParDict
{ hdr dictionary transportProperties; echo "transportModel Newtonian; nu [0 2 -1 0 0 0 0] $nu;"; } >constant/transportProperties
{ hdr dictionary turbulenceProperties; echo "simulationType laminar;"; } >constant/turbulenceProperties
{ hdr volVectorField U; cat <<END
dimensions [0 1 -1 0 0 0 0];
internalField uniform ($U 0 0);
boundaryField
{
    inlet  { type fixedValue; value uniform ($U 0 0); }
    outlet { type zeroGradient; }
    walls  { type fixedValue; value uniform ($U 0 0); }
    ball   { type noSlip; }
}
END
} >0/U
{ hdr volScalarField p; cat <<'END'
dimensions [0 2 -2 0 0 0 0];
internalField uniform 0;
boundaryField
{
    inlet  { type zeroGradient; }
    outlet { type fixedValue; value uniform 0; }
    walls  { type zeroGradient; }
    ball   { type zeroGradient; }
}
END
} >0/p
blockMesh >log.blockMesh 2>&1 || { cat log.blockMesh >&2; exit 1; }
snappyHexMesh -overwrite >log.snappy 2>&1 || { tail -20 log.snappy >&2; exit 1; }
cells=$(checkMesh 2>/dev/null | awk '/cells:/{print $2; exit}')
decomposePar -force >log.decompose 2>&1 || { cat log.decompose >&2; exit 1; }
read -r -a mpi_flags <<<"${MPIRUN_FLAGS:---allow-run-as-root --oversubscribe}"
mpirun "${mpi_flags[@]}" -n 2 simpleFoam -parallel >log.simple 2>&1 || { tail -20 log.simple >&2; exit 1; }
grep -q "SIMPLE solution converged" log.simple || { echo "openfoam_sphere_duct.sh: simpleFoam did not converge in 5000 iterations" >&2; exit 1; }
iterations=$(grep -c "^Time =" log.simple)
drag=$(tail -1 postProcessing/forces/0/force.dat | tr -d '()' | awk '{print $2}')
echo "openfoam_duct rho=$rho mu=$mu U=$U level=$level cells=$cells iterations=$iterations drag=$drag"
