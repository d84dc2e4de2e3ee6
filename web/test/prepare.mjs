// Writes the fixtures before the tests run in parallel (make test-web), so they are written once.
import { fixtures } from "./helpers.mjs";

console.log(`fixtures: ${fixtures()}`);
