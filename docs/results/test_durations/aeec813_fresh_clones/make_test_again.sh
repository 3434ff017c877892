for label in new_warm base_warm new_warm base_warm; do
  d=/tmp/fc_$label; s=$(date +%s.%N)
  (cd $d && make test > /work/notes/ab_${label}_$(date +%H%M).txt 2>&1)
  echo "$label $(git -C $d rev-parse --short HEAD) $(echo "$(date +%s.%N) - $s" | bc)" >> /work/notes/ab_summary.txt
done
